"""Where the tests find this checkout and the team folder beside it (paper, real G1 model, mocap
clips). Tests only: product code never reads the team folder."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent.parent


def _team_shared() -> Path:
    """The team folder (paper, real G1 model, mocap clips): $SAFEMIMIC_TEAM_SHARED, else beside the
    checkout, else /work/shared (where CI's clean clone may live elsewhere). Tests only."""
    candidates = [os.environ.get("SAFEMIMIC_TEAM_SHARED"), REPO.parent / "shared", "/work/shared"]
    for candidate in candidates:
        if candidate and (Path(candidate) / "robots" / "unitree_g1").is_dir():
            return Path(candidate)
    return REPO.parent / "shared"


TEAM_SHARED = _team_shared()
G1_MJCF = TEAM_SHARED / "robots" / "unitree_g1" / "g1.xml"
MOCAP_DIR = TEAM_SHARED / "data" / "mocap"
