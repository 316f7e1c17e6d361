import sys

from hsicam.cli import main

sys.exit(main())
