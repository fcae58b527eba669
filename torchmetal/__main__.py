import sys

from torchmetal.cli import main

sys.exit(main())
