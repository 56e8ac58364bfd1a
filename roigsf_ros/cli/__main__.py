"""``python -m roigsf_ros.cli``: the ``roigsf`` command from a source tree."""

import sys

from roigsf_ros.cli import main

sys.exit(main())
