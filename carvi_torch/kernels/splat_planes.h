// The selection's projection of voxel proposals onto the three principal planes (carvi_torch.select._splat)
// in plain C++: for every boundary voxel of a grid (occupied, with an empty voxel or the grid's edge among its
// 26 neighbours: select.boundary_voxels) and each of its m_d m_h m_w sub-voxel points, the point's three plane
// coordinates are read from the per-axis lookup tables (select._axis_tables) and summed in float32 in the
// torch code's order, (Ld + Lh) + Lw, rounded half to even (std::nearbyint in the default rounding mode, as
// torch.round), clamped to [-1, G] (a coordinate that is not a number goes to -1, off the plane) and the
// sample of each plane set. Equal to the torch code bit for bit: the same float32 sums, the same rounding.
#pragma once

#include <cmath>
#include <cstdint>

namespace carvi_splat {

// Whether voxel (d, h, w) of the grid g (D x H x W bytes, 1 = occupied) is occupied with an empty voxel or the
// grid's edge among its 26 neighbours.
inline bool is_boundary(const uint8_t *g, int64_t D, int64_t H, int64_t W, int64_t d, int64_t h, int64_t w)
{
    if (!g[(d * H + h) * W + w])
        return false;
    if (d == 0 || h == 0 || w == 0 || d == D - 1 || h == H - 1 || w == W - 1)
        return true;
    for (int64_t dd = d - 1; dd <= d + 1; ++dd)
        for (int64_t hh = h - 1; hh <= h + 1; ++hh) {
            const uint8_t *row = g + (dd * H + hh) * W + (w - 1);
            if (!row[0] || !row[1] || !row[2])
                return true;
        }
    return false;
}

inline int64_t sample_index(float u, int64_t G)
{
    if (!(u == u))
        return -1;
    const float k = std::nearbyint(u);
    return k < -1.0f ? -1 : (k > float(G) ? G : int64_t(k));
}

// One grid: b its position among the tables' grids (columns b * D + d, ...), out its three (G + 2)^2 planes
// (a one-sample border on each side; index (k_a + 1) + (G + 2) (k_b + 1) of plane j, whose coordinates are
// (a, b) = ((j + 1) % 3, (j + 2) % 3)).
inline void splat_grid(const uint8_t *g, int64_t b, int64_t D, int64_t H, int64_t W, const float *Ld, const float *Lh,
                       const float *Lw, int64_t md, int64_t mh, int64_t mw, int64_t G, int64_t nb, uint8_t *out)
{
    const int64_t Gp = G + 2, plane = Gp * Gp;
    const int64_t cd = nb * D, ch = nb * H, cw = nb * W;  // row lengths of the three tables
    for (int64_t d = 0; d < D; ++d)
        for (int64_t h = 0; h < H; ++h)
            for (int64_t w = 0; w < W; ++w) {
                if (!is_boundary(g, D, H, W, d, h, w))
                    continue;
                for (int64_t id = 0; id < md; ++id)
                    for (int64_t ih = 0; ih < mh; ++ih)
                        for (int64_t iw = 0; iw < mw; ++iw) {
                            int64_t k[3];
                            for (int c = 0; c < 3; ++c) {
                                const float s = Ld[(c * md + id) * cd + b * D + d] + Lh[(c * mh + ih) * ch + b * H + h];
                                k[c] = sample_index(s + Lw[(c * mw + iw) * cw + b * W + w], G);
                            }
                            for (int j = 0; j < 3; ++j)
                                out[j * plane + (k[(j + 1) % 3] + 1) + Gp * (k[(j + 2) % 3] + 1)] = 1;
                        }
            }
}

} // namespace carvi_splat
