import sys

from cdrb_cli.cli import main

sys.exit(main())
