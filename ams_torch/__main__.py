"""``python -m ams_torch ...`` runs the ``ams-torch`` command line."""
import sys

from ams_torch.apps.cli import main

sys.exit(main())
