"""``python -m suite`` = the ``splitbench`` command."""
import sys

from suite.harness.cli import main

sys.exit(main())
