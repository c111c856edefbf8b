"""sdf.py: exact distance maps against scipy, on CPU and through the torch path."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from carvi_torch import sdf
from conftest import requires_cuda


def _random_masks(g, n=6, h=33, w=41):
    m = torch.rand(n, h, w, generator=g) > 0.93
    m[1] = False  # empty
    m[2] = True  # full
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    m[3] = ((yy - 15) ** 2 / 80 + (xx - 20) ** 2 / 200) < 1
    return m


class TestDistanceToMask:
    def test_against_scipy(self, generator):
        m = _random_masks(generator)
        d = sdf.distance_to_mask(m)
        for i in range(len(m)):
            if m[i].any():
                ref = ndimage.distance_transform_edt(~m[i].numpy())
                assert np.abs(d[i].numpy() - ref).max() < 1e-4
            else:
                assert torch.isinf(d[i]).all()

    def test_torch_path_against_scipy(self, generator):
        m = _random_masks(generator)
        ok = m.flatten(1).any(1)
        got = sdf.edt_torch(m[ok])
        ref = sdf.edt_scipy(m[ok].numpy())
        assert (got - torch.from_numpy(ref)).abs().max() < 1e-4

    def test_known_value(self):
        m = torch.zeros(1, 5, 5, dtype=torch.bool)
        m[0, 0, 0] = True
        assert abs(float(sdf.distance_to_mask(m)[0, 3, 4]) - 5.0) < 1e-6

    def test_exceptions(self):
        with pytest.raises(ValueError):
            sdf.distance_to_mask(torch.zeros(4, 4, dtype=torch.bool))


class TestSignedDistance:
    def test_sign_and_half_pixel(self, generator):
        m = _random_masks(generator)
        s = sdf.signed_distance(m)
        nonempty = m.flatten(1).any(1)
        assert ((s < 0) == m)[nonempty].all()

    def test_brute_force(self, generator):
        """Tiny masks against a per-pixel loop (the ring just outside the image counts as background)."""
        m = torch.rand(3, 7, 9, generator=generator) > 0.5
        m[2, 1:6, 2:8] = True
        s = sdf.signed_distance(m)
        for n in range(3):
            mk = np.pad(m[n].numpy(), 1)
            fg = np.argwhere(mk)
            bg = np.argwhere(~mk)
            for i in range(7):
                for j in range(9):
                    p = np.array([i + 1, j + 1])
                    if mk[i + 1, j + 1]:
                        ref = -(np.sqrt(((bg - p) ** 2).sum(1)).min() - 0.5)
                    else:
                        ref = np.sqrt(((fg - p) ** 2).sum(1)).min() - 0.5
                    assert abs(float(s[n, i, j]) - ref) < 1e-5

    def test_inside_against_scipy(self, generator):
        m = _random_masks(generator)[3:4]
        s = sdf.signed_distance(m)[0].numpy()
        inside = ndimage.distance_transform_edt(np.pad(m[0].numpy(), 1))[1:-1, 1:-1]
        outside = ndimage.distance_transform_edt(~m[0].numpy())
        ref = np.where(m[0].numpy(), -(inside - 0.5), outside - 0.5)
        assert np.abs(s - ref).max() < 1e-4

    def test_lipschitz(self, generator):
        s = sdf.signed_distance(_random_masks(generator)[3:4])[0]
        assert (s[:, 1:] - s[:, :-1]).abs().max() <= 1.0 + 1e-5
        assert (s[1:] - s[:-1]).abs().max() <= 1.0 + 1e-5

    def test_given_outside_distances_are_reused(self, generator):
        m = _random_masks(generator)
        out = sdf.distance_to_mask(m)
        assert torch.equal(sdf.signed_distance(m, outside=out), sdf.signed_distance(m))
        # the given map is what is used (not recomputed)
        torch.testing.assert_close(sdf.signed_distance(m, outside=out + 1.0)[~m], sdf.signed_distance(m)[~m] + 1.0,
                                   atol=1e-5, rtol=0)
        with pytest.raises(ValueError, match="outside"):
            sdf.signed_distance(m, outside=out[:2])

    @requires_cuda
    def test_cuda_matches_cpu(self, generator):
        m = _random_masks(generator)
        a = sdf.signed_distance(m)
        b = sdf.signed_distance(m.cuda()).cpu()
        fin = torch.isfinite(a)
        assert torch.equal(fin, torch.isfinite(b)) and (a[fin] - b[fin]).abs().max() < 1e-4
