import sys

from imssr.console import main

sys.exit(main())
