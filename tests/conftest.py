from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"measured data not present at {DATA}")
    return DATA


@pytest.fixture(scope="session")
def paper_sessions():
    """Three simulated paper sessions and their batch results (shared: the batch takes ~0.5 s each)."""
    from onlinecal.batch import run_batch
    from onlinecal.sim import simulate

    out = []
    for seed in (11, 12, 13):
        sim = simulate("paper", seed)
        out.append((sim, run_batch([sim.data])))
    return out
