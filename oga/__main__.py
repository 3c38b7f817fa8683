import sys

from oga.cli import main

sys.exit(main())
