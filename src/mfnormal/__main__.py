import sys

from mfnormal.cli.commands import main

sys.exit(main())
