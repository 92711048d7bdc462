import sys

from mehs.cli import main

sys.exit(main())
