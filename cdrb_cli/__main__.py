import sys

if __name__ == "__main__":  # a spawned worker (cdrb collect --workers) imports this module again: run nothing then
    from cdrb_cli.launch import main

    sys.exit(main())
