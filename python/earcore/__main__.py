import sys

from earcore.cli import main

sys.exit(main())
