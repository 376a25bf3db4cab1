"""``python -m cylsfm.cli`` (and ``torchrun ... -m cylsfm.cli``): the ``cylsfm`` command."""

import sys

from . import main

sys.exit(main())
