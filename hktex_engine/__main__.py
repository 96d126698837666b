import sys

from hktex_engine.cli import main

sys.exit(main())
