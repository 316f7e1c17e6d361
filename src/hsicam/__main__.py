import sys

from hsicam.cli import entry

sys.exit(entry())
