import sys

from tiledsm.cli import main

sys.exit(main())
