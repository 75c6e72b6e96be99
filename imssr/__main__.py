import sys

from imssr.cli import main

sys.exit(main())
