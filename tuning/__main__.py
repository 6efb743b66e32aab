"""``python -m tuning``: the ``jaxcart`` command line."""

import sys

from tuning.commands.main import main

sys.exit(main())
