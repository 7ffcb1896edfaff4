import sys

from femreg.cli import main

if __name__ == "__main__":  # python -m femreg.cli; importing the module (e.g. to document it) runs nothing
    sys.exit(main())
