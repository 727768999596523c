"""HWP synchronous signal x TES nonlinearity for LiteBIRD: simulate, require, diagnose.

The logic of every workflow stage lives here; ``workflow/scripts`` only call it.
"""

__version__ = "0.1.0"

from . import _moved

_moved.install()  # the modules moved into subpackages after 0.1.0 keep their old names
