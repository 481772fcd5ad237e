"""The command `python -m gesture.realism`; the code is `gesture.eval.realism`."""

import sys

from gesture.eval.realism import main

if __name__ == "__main__":
    sys.exit(main())
