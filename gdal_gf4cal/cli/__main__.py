"""``python -m gdal_gf4cal.cli``: the same as the ``gf4cal`` command."""
import sys

from . import main

sys.exit(main())
