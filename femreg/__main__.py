import sys

from femreg.cli import main

if __name__ == "__main__":  # python -m femreg, the same as the femreg command
    sys.exit(main())
