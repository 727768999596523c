"""HWP synchronous signal x TES nonlinearity for LiteBIRD: simulate, require, diagnose.

The logic of every workflow stage lives here; ``workflow/scripts`` only call it.
"""

__version__ = "0.2.0"
