import sys

from octolog.shell.cli import main

sys.exit(main())
