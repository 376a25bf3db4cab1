import pytest

from cylsfm.data.synth import SynthConfig, generate_dataset


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    """Two short rides at 128x32 with ground truth (generated once per test session)."""
    root = tmp_path_factory.mktemp("tiny_data")
    generate_dataset(
        root,
        sequences=2,
        frames=10,
        width=128,
        height=32,
        seed=11,
        workers=1,
        progress=False,
        config=SynthConfig(stop_probability=0.0),
    )
    return root
