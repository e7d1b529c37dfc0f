"""``python -m msf_torch ...``: the ``msf`` command line (:func:`msf_torch.cli.main`)."""

from __future__ import annotations

import sys

from msf_torch.cli import main

if __name__ == "__main__":
    sys.exit(main())
