"""IM-NET's networks: shapes and the output activation."""

import pytest
import torch

from ngp_mi.nets.imnet import ImplicitDecoder, LatentCritic, LatentGenerator, VoxelEncoder, leaky_clamp


def test_network_shapes_and_imnet_output_activation():
    enc, dec = VoxelEncoder(32, ef=4, code_dim=16), ImplicitDecoder(16, gf=4, fourier_levels=2)
    code = enc(torch.rand(2, 1, 32, 32, 32))
    assert code.shape == (2, 16) and bool(((code > 0) & (code < 1)).all())
    assert dec(torch.rand(2, 100, 3) - 0.5, code).shape == (2, 100, 1)
    assert LatentGenerator(8, 32, 16)(torch.randn(5, 8)).shape == (5, 16)
    assert LatentCritic(16, 32)(torch.rand(5, 16)).shape == (5,)
    x = torch.tensor([-1.0, 0.0, 0.3, 1.0, 2.0])
    assert torch.allclose(leaky_clamp(x), torch.tensor([-0.01, 0.0, 0.3, 1.0, 1.01]))
    with pytest.raises(ValueError, match="multiple of 16"):
        VoxelEncoder(16)
