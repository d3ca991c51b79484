import sys

from rough_map.cli.main import main

sys.exit(main())
