"""``python -m femcal`` runs the command line."""

import sys

from femcal.cli import main

sys.exit(main())
