import sys

from denoisers.cli import main

sys.exit(main())
