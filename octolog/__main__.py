import sys

from octolog.cli import main

sys.exit(main())
