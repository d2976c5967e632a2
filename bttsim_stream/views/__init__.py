from ._legacy import *  # noqa: F401,F403  (split pending)
from ._legacy import LiveViews, open_recording, log_recording, build_blueprint  # noqa: F401
