import sys

from denoisers.cli import main

if __name__ == "__main__":      # not when a child process (multiprocessing) imports the main module
    sys.exit(main())
