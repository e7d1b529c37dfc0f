"""Train the covariance network through the differentiable ESKF (LightningCLI).

Usage::

    python training/train.py fit --config training/configs/default.yaml
    python training/train.py fit --config training/configs/smoke.yaml --trainer.max_epochs 2
    python training/train.py fit --config training/configs/kitti.yaml

Any ``--model.*``, ``--data.*`` or ``--trainer.*`` argument overrides the config
(:class:`msf_torch.learning.module.CovNetModule`,
:class:`msf_torch.learning.data.RunDataModule`, ``lightning.Trainer``). A config may name a
subclass of either with ``class_path`` / ``init_args`` (``training/configs/kitti.yaml``:
:class:`msf_torch.learning.kitti.KittiCovNetModule` and
:class:`msf_torch.learning.kitti.KittiDataModule`); without ``class_path`` the two base
classes are used. TensorBoard logs go
to ``runs/`` (``tensorboard --logdir runs``); the trained network is written to
``<log_dir>/covnet.pt`` (:func:`msf_torch.learning.load_checkpoint`). Bad input data (a
run without ground truth, too short, at another IMU rate, a missing file: a
:class:`~msf_torch.io.errors.DataError`) ends in one line naming the file, exit status 2.
"""

from __future__ import annotations

import sys

from lightning.pytorch.cli import LightningCLI

from msf_torch.io.errors import DataError
from msf_torch.learning.data import RunDataModule
from msf_torch.learning.module import CovNetModule


def main(args: list[str] | None = None, run: bool = True) -> LightningCLI:
    """Run the CLI on ``args`` (default: ``sys.argv[1:]``) and return it; with ``run=False``
    only parse and instantiate (``args`` then has no subcommand)."""
    return LightningCLI(
        CovNetModule,
        RunDataModule,
        subclass_mode_model=True,
        subclass_mode_data=True,
        args=args,
        run=run,
        save_config_kwargs={"overwrite": True},
    )


if __name__ == "__main__":
    try:
        main()
    except DataError as err:
        print(f"train.py: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
