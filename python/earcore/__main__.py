import sys

from earcore.app.cli import main

sys.exit(main())
