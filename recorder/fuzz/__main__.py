"""``python -m recorder.fuzz``: a fuzz run, or one saved failing case again."""

import sys

from recorder.fuzz.cli import main

if __name__ == "__main__":
    sys.exit(main())
