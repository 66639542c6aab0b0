"""Long-running checks, marked slow (``make test-slow``)."""

import pytest
from helpers import rss_mib

from ngp_mi.data.render_dataset import DatasetConfig, render_dataset


@pytest.mark.slow
def test_dataset_memory_stays_flat_over_2000_views(tmp_path):
    """200 shapes (a new Mitsuba scene each) x 10 views: resident memory must not grow."""
    samples = []
    for chunk in range(8):
        config = DatasetConfig(source="chair", num_shapes=25, views=10, resolution=64, seed=1000 * chunk)
        summary = render_dataset(config, tmp_path / str(chunk), progress=False)
        assert summary["views_rendered"] == 250
        samples.append(rss_mib())
    # 5 MiB: a kernel compiled per shape (a literal in the trace) grew it by 14 MiB over these views
    assert samples[-1] - samples[0] < 5, f"RSS after each 250 views: {samples}"
