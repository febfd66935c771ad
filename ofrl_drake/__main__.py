"""``python -m ofrl_drake`` is the ``ofrl-drake`` command."""

import sys

from ofrl_drake.cli import main

sys.exit(main())
