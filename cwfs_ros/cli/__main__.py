"""``python -m cwfs_ros.cli``: the ``cwfs-ros`` command."""

import sys

from cwfs_ros.cli.main import main

sys.exit(main())
