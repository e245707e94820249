import os

import matplotlib
import pytest

matplotlib.use("Agg")
os.environ.setdefault("PRSA_FAST", "1")


@pytest.fixture(scope="session")
def paper_plant():
    from prsa_ctrl import load_plant

    return load_plant("paper-iprsm")


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import matplotlib.pyplot as plt

    plt.close("all")
