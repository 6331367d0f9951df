"""``python -m taskvar_torch.cli``: the ``taskvar`` command."""

import sys

from taskvar_torch.cli import main

sys.exit(main())
