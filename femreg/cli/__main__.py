import sys

from femreg.cli import main

sys.exit(main())
