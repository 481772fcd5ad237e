"""The command `python -m gesture.suite`; the code is `gesture.eval.suite`."""

import sys

from gesture.eval.suite import main

if __name__ == "__main__":
    sys.exit(main())
