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
``<log_dir>/covnet.pt`` (:func:`msf_torch.learning.load_checkpoint`).
"""

from __future__ import annotations

from lightning.pytorch.cli import LightningCLI

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
    main()
