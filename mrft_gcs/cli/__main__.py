import sys

from mrft_gcs.cli import main

sys.exit(main())
