"""Live reconstruction (``stereoseed live``): photos inserted as they arrive in a watched
folder, the model pushed to a page on 127.0.0.1, the result folder written as ``reconstruct``
writes it when the run stops (docs/live.md)."""
from stereoseed.live.config import LiveConfig
from stereoseed.live.page import LivePage
from stereoseed.live.run import run_live
from stereoseed.live.session import LiveRun
from stereoseed.live.watch import FolderWatch

__all__ = ["LiveConfig", "LivePage", "LiveRun", "FolderWatch", "run_live"]
