import sys

from cdrb_cli.cli import main

if __name__ == "__main__":  # a spawned worker (cdrb collect --workers) imports this module again: run nothing then
    sys.exit(main())
