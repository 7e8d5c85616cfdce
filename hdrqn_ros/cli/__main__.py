"""``python -m hdrqn_ros.cli``: the ``hdrqn`` command."""
import sys

from hdrqn_ros.cli import main

if __name__ == "__main__":
    sys.exit(main())
