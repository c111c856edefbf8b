"""``python -m carvi_torch.export`` (see :func:`carvi_torch.export.run.main`)."""
import sys

from .run import main

if __name__ == "__main__":
    sys.exit(main())
