"""The command `python -m gesture.evaluate`; the code is `gesture.eval.evaluate`."""

import sys

from gesture.eval.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
