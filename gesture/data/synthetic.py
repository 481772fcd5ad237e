"""The command `python -m gesture.data.synthetic`; the code is `gesture.synth.build`."""

import sys

from gesture.synth.build import main

if __name__ == "__main__":
    sys.exit(main())
