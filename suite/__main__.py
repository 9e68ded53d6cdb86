"""``python -m suite`` = the ``splitbench`` command."""
import sys

from suite.cli import main

sys.exit(main())
