"""The command `python -m gesture.train_lm`; the code is `gesture.lm.train`."""

import sys

from gesture.lm.train import main

if __name__ == "__main__":
    sys.exit(main())
