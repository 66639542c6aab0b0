import numpy as np
import pytest
import torch
from PIL import Image
from torch.utils.data import DataLoader

from ngp_mi.data.datasets import DepthDataset, ImageFolderDataset, ReflectanceMapDataset
from ngp_mi.data.exr import read_exr, write_exr
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    render_dataset(DatasetConfig(source="chair", num_shapes=2, views=3, resolution=24, real_spp=2), root,
                   progress=False)
    return root


def test_reflectance_maps_match_the_files(dataset):
    ds = ReflectanceMapDataset(dataset)
    assert len(ds) == 6
    item = ds[4]
    assert item["depth"].shape == (1, 24, 24) and item["normal"].shape == (3, 24, 24)
    assert item["K"].shape == (3, 3) and item["E"].shape == (3, 4)
    exr = read_exr(dataset / ds.records[4]["files"]["maps"])
    np.testing.assert_array_equal(item["albedo"].permute(1, 2, 0).numpy(), exr["albedo"])
    batch = next(iter(DataLoader(ds, batch_size=4)))
    assert batch["noc"].shape == (4, 3, 24, 24) and len(batch["shape_id"]) == 4
    with pytest.raises(ValueError, match="not"):
        ReflectanceMapDataset(dataset, channels=("depth", "specular"))


def test_depth_dataset(dataset):
    item = DepthDataset(dataset)[0]
    assert set(item) >= {"depth", "mask", "K", "E"} and "normal" not in item


def test_image_folder_from_dataset_and_photos_with_flips(dataset, tmp_path):
    real = ImageFolderDataset(dataset, flip=False)
    assert len(real) == 6 and real[0].shape == (3, 24, 24) and 0 <= real[0].min() and real[0].max() <= 1
    photos = tmp_path / "photos"
    photos.mkdir()
    gradient = np.tile(np.linspace(0, 255, 40, dtype=np.uint8), (30, 1))
    Image.fromarray(np.stack([gradient] * 3, -1)).save(photos / "a.png")
    write_exr(photos / "b.exr", {"rgb": np.full((30, 40, 3), 0.18)})
    ds = ImageFolderDataset(photos, size=16, flip=True, generator=torch.Generator().manual_seed(0))
    images = [ds[0] for _ in range(20)]
    assert all(im.shape == (3, 16, 16) for im in images)
    left_bright = [bool(im[0, :, 0].mean() > im[0, :, -1].mean()) for im in images]
    assert any(left_bright) and not all(left_bright)  # some flipped, some not
    assert ds[1].mean().item() == pytest.approx(0.4614, abs=2e-3)  # linear 0.18 shown as sRGB
    (photos / "c.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match="c.png: unreadable image"):
        ImageFolderDataset(photos)[2]


def test_views_with_their_coarse_depth(dataset, tmp_path):
    """WithCoarseDepth pairs views by (shape id, view): a folder of fewer views fails naming the first
    missing one, or, with drop_unpaired, leaves those views out and counts them."""
    from ngp_mi.data.datasets import WithCoarseDepth

    fewer = tmp_path / "fewer"  # the same two chairs, two of their three views
    render_dataset(DatasetConfig(source="chair", num_shapes=2, views=2, resolution=24, channels=("depth", "mask")),
                   fewer, progress=False)
    views = ReflectanceMapDataset(dataset)
    with pytest.raises(ValueError, match=r"no coarse view for shape 'chair/00000\d' view 2"):
        WithCoarseDepth(views, fewer)
    paired = WithCoarseDepth(views, fewer, drop_unpaired=True)
    assert len(paired) == 4 and paired.dropped == 2
    item, record = paired[3], paired.records[3]
    coarse = DepthDataset(fewer)
    twin = next(i for i, r in enumerate(coarse.records) if (r["shape_id"], r["view"]) == (record["shape_id"], record["view"]))
    assert torch.equal(item["coarse_depth"], coarse[twin]["depth"]) and item["shape_id"] == record["shape_id"]
    assert item["normal"].shape == (3, 24, 24)
