import sys

from psfd.cli import main

sys.exit(main())
