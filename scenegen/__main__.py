import sys

from scenegen.cli import main

sys.exit(main())
