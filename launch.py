"""`python launch.py ...` in a checkout is `ecas ...`: the agent's launcher (`ecas.launch`), by the design's name."""

import sys

from ecas.launch import DEFAULT_CONFIG, main, mode_overrides, parse_args

__all__ = ["DEFAULT_CONFIG", "main", "mode_overrides", "parse_args"]

if __name__ == "__main__":
    sys.exit(main())
