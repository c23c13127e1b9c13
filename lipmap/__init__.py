"""lipmap: 3D line mapping with interacted planes (LiP-Map) and line-assisted localization."""
import logging

__version__ = "0.1.0"

logger = logging.getLogger("lipmap")
if not logger.handlers:
    _handler = logging.StreamHandler()
    _handler.setFormatter(logging.Formatter("[%(asctime)s %(name)s %(levelname)s] %(message)s", "%H:%M:%S"))
    logger.addHandler(_handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False

from .errors import InputError  # noqa: E402

__all__ = ["InputError", "logger", "__version__"]
