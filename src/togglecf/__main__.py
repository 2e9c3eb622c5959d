"""``python -m togglecf …`` runs the ``togglecf`` command."""
import sys

from togglecf.cli import main

sys.exit(main())
