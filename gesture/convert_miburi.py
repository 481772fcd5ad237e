"""The command `python -m gesture.convert_miburi`; the code is `gesture.release.convert`."""

import sys

from gesture.release.convert import main

if __name__ == "__main__":
    sys.exit(main())
