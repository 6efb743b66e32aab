import sys

from jaxcart.cli import main

sys.exit(main())
