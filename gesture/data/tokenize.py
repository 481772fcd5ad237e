"""The command `python -m gesture.data.tokenize`; the code is `gesture.lm.tokenize`."""

import sys

from gesture.lm.tokenize import main

if __name__ == "__main__":
    sys.exit(main())
