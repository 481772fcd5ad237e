"""The command `python -m gesture.train_codec`; the code is `gesture.codec.train`."""

import sys

from gesture.codec.train import main

if __name__ == "__main__":
    sys.exit(main())
