"""``python -m carvi_torch.export`` (see :func:`carvi_torch.export.command.main`)."""
import sys

from .command import main

if __name__ == "__main__":
    sys.exit(main())
