import sys

from dfusion.cli import main

sys.exit(main())
