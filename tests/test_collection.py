"""collection.py: flip pairs from names, canvas maps, indexing, mirroring."""
from __future__ import annotations

import pytest
import torch

from carvi_torch.cameras import ScaledOrthographic, Similarity2D, random_rotations
from carvi_torch.collection import (ClassCollection, ClassMeta, canvas_similarity, flip_permutation,
                                    infer_flip_pairs, resample_to_canvas, resample_to_canvases, canvas_supersample)


class TestInferFlipPairs:
    @pytest.mark.parametrize("names,expected", [
        (["L_WingTip", "NoseTip", "R_WingTip"], [(0, 2)]),
        (["Left_Wing_Base", "Right_Wing_Base", "Top_Rudder"], [(0, 1)]),
        (["left_wing", "right_wing", "tail"], [(0, 1)]),
        (["body_back_left_lower", "body_back_right_lower"], [(0, 1)]),
        (["wheel_l", "wheel_r", "hub"], [(0, 1)]),
        (["leftcorner_windshield", "rightcorner_windshield"], [(0, 1)]),
        (["L_Eye", "R_Eye", "Nose", "L_EarBase", "R_EarBase"], [(0, 1), (3, 4)]),
        (["left", "right"], [(0, 1)]),
        (["mouth", "body", "bottom"], []),
        (["left_wing", "tail"], []),  # partner missing
    ])
    def test_names(self, names, expected):
        assert infer_flip_pairs(names) == expected

    def test_permutation_involution(self):
        perm = flip_permutation(6, [(0, 3), (1, 5)])
        assert torch.equal(perm[perm], torch.arange(6))
        assert perm.tolist() == [3, 5, 2, 0, 4, 1]


class TestCanvas:
    def test_similarity_centres_box(self):
        boxes = torch.tensor([[10.0, 20.0, 109.0, 69.0], [0.0, 0.0, 9.0, 39.0]])
        sim = canvas_similarity(boxes, 128, 0.1)
        c = sim.apply(torch.stack([(boxes[:, :2] + boxes[:, 2:]) / 2], dim=1))[:, 0]
        assert torch.allclose(c, torch.full((2, 2), 63.5))
        side = torch.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]) + 1
        assert torch.allclose(sim.scale * side, torch.full((2,), 128 * 0.8))

    def test_resample_identity_and_downscale(self):
        m = torch.zeros(64, 64, dtype=torch.bool)
        m[10:30, 20:50] = True
        same = resample_to_canvas(m, 1.0, torch.zeros(2), 64, supersample=1)
        assert torch.equal(same, m)
        half = resample_to_canvas(m, 0.5, torch.zeros(2), 32)
        # area-averaged: the rectangle [10, 30) x [20, 50) at half resolution is [5, 15) x [10, 25)
        ref = torch.zeros(32, 32, dtype=torch.bool)
        ref[5:15, 10:25] = True
        assert (half ^ ref).sum() <= 4


class TestResampleToCanvases:
    """The batched resampling that loading uses: the per-object reference's canvases, bit for bit."""

    def _cases(self, n, seed=0):
        g = torch.Generator().manual_seed(seed)
        masks, scales, offsets = [], [], []
        for i in range(n):
            h, w = (1, 1) if i == 0 else (1, 40) if i == 1 else torch.randint(2, 200, (2,), generator=g).tolist()
            masks.append(torch.rand(h, w, generator=g) < torch.rand((), generator=g))
            # scales 0.05-3: every sub-sampling 1-4; offsets push parts of the image off the canvas
            scales.append(float(0.05 + 2.95 * torch.rand((), generator=g) ** 2))
            offsets.append((torch.randn(2, generator=g) * 30).tolist())
        return masks, torch.tensor(scales), torch.tensor(offsets)

    def test_the_reference_bit_for_bit(self):
        masks, scale, offset = self._cases(60)
        got = resample_to_canvases(masks, scale, offset, 40)
        ref = torch.stack([resample_to_canvas(m, a, b, 40) for m, a, b in zip(masks, scale.tolist(), offset)])
        assert got.shape == (60, 40, 40) and got.dtype == torch.bool
        assert {canvas_supersample(a) for a in scale.tolist()} == {1, 2, 3, 4}
        assert ref.any() and torch.equal(got, ref)

    def test_known_values(self):
        # identity scale, no sub-sampling: the canvas is the image where they overlap
        m = torch.zeros(20, 30, dtype=torch.bool)
        m[3:9, 4:17] = True
        got = resample_to_canvases([m], torch.tensor([1.0]), torch.tensor([[2.0, 1.0]]), 24)[0]
        ref = torch.zeros(24, 24, dtype=torch.bool)
        ref[4:10, 6:19] = True
        assert torch.equal(got, ref)

    def test_masks_of_other_types_as_the_reference_reads_them(self):
        """A float mask is read as its values, as the reference reads it (not viewed as bytes)."""
        masks, scale, offset = self._cases(6, seed=1)
        as_floats = [m.float() for m in masks]
        got = resample_to_canvases(as_floats, scale, offset, 24)
        ref = torch.stack([resample_to_canvas(m, a, b, 24) for m, a, b in zip(as_floats, scale.tolist(), offset)])
        assert torch.equal(got, ref) and torch.equal(got, resample_to_canvases(masks, scale, offset, 24))

    def test_bool_masks_of_foreign_bytes_read_as_ones(self):
        """A bool tensor over bytes other than 0 and 1 (numpy's ``view(bool)``) gives the clean mask's canvas."""
        import numpy as np

        raw = (np.random.default_rng(0).random((30, 40)) < 0.5).astype(np.uint8) * 255
        dirty, clean = torch.from_numpy(raw.view(bool)), torch.from_numpy(raw != 0)
        scale, offset = torch.tensor([0.5]), torch.tensor([[3.0, 4.0]])
        got = resample_to_canvases([dirty], scale, offset, 24)[0]
        assert torch.equal(got, resample_to_canvas(clean, 0.5, [3.0, 4.0], 24))

    def test_empty_and_mismatched(self):
        assert resample_to_canvases([], torch.zeros(0), torch.zeros(0, 2), 8).shape == (0, 8, 8)
        with pytest.raises(ValueError, match="2 masks"):
            resample_to_canvases([torch.ones(3, 3, dtype=torch.bool)] * 2, torch.ones(1), torch.zeros(1, 2), 8)


def _collection(n=4, k=5, C=32, g=None):
    g = g or torch.Generator().manual_seed(0)
    meta = ClassMeta("thing", ["left_a", "right_a", "nose", "l_b", "r_b"][:k], infer_flip_pairs(
        ["left_a", "right_a", "nose", "l_b", "r_b"][:k]))
    masks = torch.rand(n, C, C, generator=g) > 0.5
    kp = torch.rand(n, k, 2, generator=g) * (C - 1)
    vis = torch.rand(n, k, generator=g) > 0.3
    sim = Similarity2D(torch.rand(n, generator=g) + 0.5, torch.randn(n, 2, generator=g))
    return ClassCollection(meta, masks, kp, vis, sim, torch.tensor([[200, 100]] * n), [10 + i for i in range(n)],
                           list(range(n)), [100 + i for i in range(n)], torch.arange(n),
                           torch.zeros(n, dtype=torch.bool), [f"s{i}" for i in range(n)])


class TestClassCollection:
    def test_shapes_and_index(self):
        c = _collection()
        sub = c[torch.tensor([True, False, True, False])]
        assert len(sub) == 2 and sub.annotation_ids == [10, 12] and sub.sources == ["s0", "s2"]
        assert len(c[1:]) == 3 and len(c[[3]]) == 1

    def test_per_row_sequences_given_as_tuples(self):
        """Sources, splits and fingerprints given as tuples: subsets, moves, mirrors and concatenations take them
        row by row, as lists."""
        c = _collection()
        c = c.replace(sources=("a", "b", "c", "d"), splits=("pool",) * 4, fingerprints=("f0", "f1", "f2", "f3"))
        assert c[[2, 0]].sources == ["c", "a"] and c[[2, 0]].fingerprints == ["f2", "f0"]
        assert c.to("cpu").splits == ["pool"] * 4 and c.mirror().sources == ["a", "b", "c", "d"]
        both = ClassCollection.cat([c[:1], c[3:]])
        assert both.sources == ["a", "d"] and both.annotation_ids == [10, 13]

    def test_bad_shapes(self):
        c = _collection()
        with pytest.raises(ValueError):
            ClassCollection(c.meta, c.masks, c.keypoints[:, :2], c.visible, c.canvas_from_image, c.image_size,
                            c.annotation_ids, c.image_ids, c.object_ids, c.object_groups, c.is_mirror)

    def test_mirror_twice_is_identity(self):
        c = _collection()
        cc = c.mirror().mirror()
        for f in ("masks", "keypoints", "visible", "image_size", "is_mirror"):
            assert torch.allclose(getattr(cc, f).float(), getattr(c, f).float(), atol=1e-5), f
        assert cc.annotation_ids == c.annotation_ids and cc.object_ids == c.object_ids
        assert torch.allclose(cc.canvas_from_image.offset, c.canvas_from_image.offset, atol=1e-4)

    def test_mirror_swaps_labels(self):
        c = _collection()
        m = c.mirror()
        assert torch.equal(m.masks, c.masks.flip(-1)) and m.is_mirror.all()
        # left_a of the mirror is right_a of the original, flipped
        assert torch.allclose(m.keypoints[:, 0, 0], c.canvas_size - 1 - c.keypoints[:, 1, 0])
        assert torch.equal(m.visible[:, 0], c.visible[:, 1])
        assert len(c.with_mirrors()) == 2 * len(c)

    def test_mirror_consistent_with_cameras(self):
        """Mirrored canvas keypoints = mirrored image camera, composed with the mirrored canvas map."""
        g = torch.Generator().manual_seed(1)
        n, C = 3, 64
        names = ["left_a", "right_a", "nose"]
        X = torch.tensor([[-1.0, 0.2, 0.3], [1.0, 0.2, 0.3], [0.0, -1.0, 0.1]])  # symmetric about x = 0
        P = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))
        cam = ScaledOrthographic(random_rotations(n, g), torch.full((n,), 40.0), torch.full((n, 2), 100.0))
        img_kp = cam.project(X)
        sim = Similarity2D(torch.full((n,), 0.3), torch.full((n, 2), 2.0))
        meta = ClassMeta("t", names, infer_flip_pairs(names))
        coll = ClassCollection(meta, torch.zeros(n, C, C, dtype=torch.bool), sim.apply(img_kp),
                               torch.ones(n, 3, dtype=torch.bool), sim, torch.tensor([[250, 180]] * n),
                               list(range(n)), list(range(n)), list(range(n)), torch.arange(n),
                               torch.zeros(n, dtype=torch.bool))
        m = coll.mirror()
        cam_m = cam.mirror(250.0, P).compose_similarity(m.canvas_from_image)
        assert torch.allclose(cam_m.project(X), m.keypoints, atol=1e-4)
        assert torch.allclose(m.keypoints_in_image(), cam.mirror(250.0, P).project(X), atol=1e-4)

    def test_to_device(self):
        c = _collection().to("cpu")
        assert c.device.type == "cpu"
