"""``python -m carvi_torch.report --recon DIR [--out DIR/report]``."""
import sys

from . import main

if __name__ == "__main__":
    sys.exit(main())
