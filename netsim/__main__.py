"""``python -m netsim transfer ...`` / ``python -m netsim validate ...`` (same as ``splitbench netsim ...``)."""

import sys

from netsim.cli import main

sys.exit(main())
