import sys

from torchtrack.cli import main

sys.exit(main())
