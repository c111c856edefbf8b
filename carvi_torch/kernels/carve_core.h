/* Fused cone-cost carving on the CPU: sampling, maximum and labels per column, with early exit.
 *
 * The arithmetic of carvi_torch's carving kernel (formerly kernels/carve_fused.c, a C99 file loaded with
 * ctypes), as a C++ header for carve_native.cpp, which wraps it in torch.library operators. The code is
 * that file's, operation for operation; what changed is only C++ spelling (restrict, the packing table
 * built at compile time instead of by a constructor) and the entry points (see the end of the file).
 *
 * Computes the labels of carvi_torch's carve_proposals (bilinear maps, imprinting or not) without
 * materialising the cost C. For each proposal and each foreground column of its reference:
 *
 *   1. The column's depths start as candidates. Each view in turn is sampled at the remaining
 *      candidates only, the running maximum C is updated, and the depths where it reached >= 0
 *      (exterior: C is a maximum, so it can only grow) are dropped. The depths left after the
 *      last view are the interior voxels, exactly.
 *   2. A column left without an interior voxel that must be imprinted needs the first depth of
 *      minimal C, so it is sampled again at every depth and view (no early exit).
 *
 * Views are tried in an order that adapts per proposal: the view that dropped the most depths
 * in the previous column goes first. C is a maximum, so the order changes which samples are
 * read, never the labels.
 *
 * The arithmetic is that of the torch path, operation for operation, in float32 (compile with
 * -ffp-contract=off): sampling coordinates (G0 d) + ((G1 h + G2 w) + G3), then grid_sample's
 * align_corners=True, padding_mode="border" bilinear read of the scaled map (each pixel value
 * times the view's scale, as the torch path scales a map before sampling it). torch's
 * vectorised CPU kernel sums the four weighted pixels with fused multiply-adds where it is
 * built for FMA (AVX2, AVX-512); the `fma` variant below does the same, the `plain` variant
 * does not, and the loader keeps the variant whose samples equal grid_sample's bit for bit.
 * The one difference: where a pixel's east or south neighbour lies beyond the map, torch reads
 * 0 and this kernel the pixel itself; its weight is exactly 0 there (the coordinate is clamped
 * to the last pixel), so only the sign of a zero sum can differ, which no label sees.
 *
 * Memory safety: every coordinate is clamped into the map before it is truncated (NaN to 0), so a
 * read stays inside the map it samples, except that the AVX2 sampler reads each row's two pixels
 * as one 8-byte load: at a map's last pixel it reads one float beyond it (weight 0). The caller
 * must provide that float after the last map it samples (carve_native.cpp copies the maps when a
 * view uses the last one).
 *
 * Layouts (all C-contiguous):
 *   ext      (K, Hp, Wp) float32   extended, unscaled maps
 *   views    (B, V) int64          row of ext per view slot, < 0 for a slot to skip
 *   scale    (B, V) float32        per-slot scale of the map values
 *   G        (B, V, 2, 4) float32  voxel index -> grid_sample coordinates, per slot
 *   colcost  (B, n*n) float32      reference cost at the column centres (foreground iff < 0)
 *   occ      (B, n, n*n) uint8     out, zero on entry: interior voxels
 *   columns  (B, n*n) uint8        out, zero on entry: columns holding an interior voxel
 *   nonempty (B,) uint8            out: any interior voxel
 *   samples  (B,) int64            out: bilinear samples read per proposal
 */
#pragma once
#include <stdint.h>

#define CARVI_MAX_VIEWS 64
#define CARVI_MAX_RESOLUTION 2048

/* x86 with AVX2 code paths (CARVI_NO_X86 builds the portable code alone, as on other processors).
 * MSVC has no target attributes: it builds the portable code (not tried: no Windows machine here). */
#if (defined(__x86_64__) || defined(__i386__)) && !defined(CARVI_NO_X86) && !defined(_MSC_VER)
#define CARVI_X86 1
#endif

#if defined(_MSC_VER) && !defined(__clang__)
#include <cmath>
#define CARVI_RESTRICT __restrict
#define CARVI_INLINE static __forceinline
#define CARVI_FMAF(a, b, c) std::fma((float)(a), (float)(b), (float)(c))
#else
#define CARVI_RESTRICT __restrict__
#define CARVI_INLINE static inline __attribute__((always_inline))
#define CARVI_FMAF(a, b, c) __builtin_fmaf(a, b, c)
#endif

#if defined(CARVI_X86)
#define CARVI_FMA_TARGET __attribute__((target("avx2,fma")))
#else
#define CARVI_FMA_TARGET
#endif

namespace carvi {

typedef struct {
    const float *map;
    float scale, g0x, g0y, g1x, g1y, g2x, g2y, g3x, g3y;
} view_t;

typedef struct {
    int64_t Hp, Wp;
    float sfx, sfy, maxx, maxy;
} geom_t;

/* out[i] = the scaled map's bilinear sample at depth idx[i] of the column whose in-plane
 * coordinate terms are (cx, cy): grid_sample(..., "bilinear", "border", align_corners=True).
 * A plain loop without branches, so that the compiler vectorises it. */
CARVI_INLINE void sample_depths(const view_t *v, const geom_t *g, float cx, float cy,
                                const int32_t *CARVI_RESTRICT idx, int m, float *CARVI_RESTRICT out, const int fused)
{
    const float *CARVI_RESTRICT map = v->map;
    const float scale = v->scale, g0x = v->g0x, g0y = v->g0y;
    const float sfx = g->sfx, sfy = g->sfy, maxx = g->maxx, maxy = g->maxy;
    const int32_t Wp = (int32_t)g->Wp, Hp = (int32_t)g->Hp;
    for (int i = 0; i < m; i++) {
        float df = (float)idx[i];
        float gx = g0x * df, gy = g0y * df;
        gx = gx + cx;
        gy = gy + cy;
        float x = (gx + 1.0f) * sfx;
        float y = (gy + 1.0f) * sfy;
        x = x > 0.0f ? x : 0.0f; /* clamp to [0, max]; a NaN to 0, as torch */
        y = y > 0.0f ? y : 0.0f;
        x = x < maxx ? x : maxx;
        y = y < maxy ? y : maxy;
        int32_t ix = (int32_t)x, iy = (int32_t)y; /* x, y >= 0: truncation is the floor */
        float w = x - (float)ix, n = y - (float)iy;
        float e = 1.0f - w, s = 1.0f - n;
        float nw = s * e, ne = s * w, sw = n * e, se = n * w;
        int32_t o = iy * Wp + ix;
        int32_t oe = ix + 1 < Wp ? 1 : 0; /* beyond the map: the pixel itself, with weight 0 */
        int32_t os = iy + 1 < Hp ? Wp : 0;
        float vnw = map[o] * scale, vne = map[o + oe] * scale;
        float vsw = map[o + os] * scale, vse = map[o + os + oe] * scale;
        if (fused)
            out[i] = CARVI_FMAF(vse, se, CARVI_FMAF(vsw, sw, CARVI_FMAF(vne, ne, vnw * nw)));
        else
            out[i] = ((vnw * nw + vne * ne) + vsw * sw) + vse * se;
    }
}

/* Candidates i0 <= i < na: cost[i] = max(cost[i], s[i]); keeps (in order, from position m) those
 * whose cost is still < 0. Returns the new count. */
CARVI_INLINE int keep_negative(int32_t *CARVI_RESTRICT idx, float *CARVI_RESTRICT cost,
                               const float *CARVI_RESTRICT s, int m, int i0, int na)
{
    for (int i = i0; i < na; i++) {
        float c = s[i] > cost[i] ? s[i] : cost[i];
        idx[m] = idx[i];
        cost[m] = c;
        m += c < 0.0f;
    }
    return m;
}

#if defined(CARVI_X86)
} // namespace carvi
#include <immintrin.h>
namespace carvi {

/* Left-packing permutations for 8 lanes: entry `mask` moves the lanes whose bit is set to the front
 * (built by the compiler: no constructor, no initialisation order to get right). */
struct pack_lut_t {
    int32_t lane[256][8];
};
static constexpr pack_lut_t make_pack_lut()
{
    pack_lut_t t{};
    for (int mask = 0; mask < 256; mask++) {
        int k = 0;
        for (int lane = 0; lane < 8; lane++)
            if (mask >> lane & 1)
                t.lane[mask][k++] = lane;
    }
    return t;
}
alignas(32) static constexpr pack_lut_t pack_lut = make_pack_lut();

/* keep_negative, eight candidates at a time (AVX2 left-packing); the same result. */
__attribute__((target("avx2,fma"))) static inline int keep_negative_avx2(int32_t *CARVI_RESTRICT idx,
                                                                          float *CARVI_RESTRICT cost,
                                                                          const float *CARVI_RESTRICT s, int na)
{
    int m = 0, i = 0;
    const __m256 zero = _mm256_setzero_ps();
    for (; i + 8 <= na; i += 8) {
        __m256 sv = _mm256_loadu_ps(s + i), cv = _mm256_loadu_ps(cost + i);
        __m256 c = _mm256_blendv_ps(cv, sv, _mm256_cmp_ps(sv, cv, _CMP_GT_OQ)); /* s > cost ? s : cost */
        int mask = _mm256_movemask_ps(_mm256_cmp_ps(c, zero, _CMP_LT_OQ));
        __m256i perm = _mm256_loadu_si256((const __m256i *)pack_lut.lane[mask]);
        __m256i iv = _mm256_loadu_si256((const __m256i *)(idx + i));
        /* m <= i: the stores only overwrite lanes already read */
        _mm256_storeu_si256((__m256i *)(idx + m), _mm256_permutevar8x32_epi32(iv, perm));
        _mm256_storeu_ps(cost + m, _mm256_permutevar8x32_ps(c, perm));
        m += __builtin_popcount((unsigned)mask);
    }
    return keep_negative(idx, cost, s, m, i, na);
}

/* The two pixels (p[0], p[1]) of 8 lanes, as (first, second) vectors in lane order. */
__attribute__((target("avx2,fma"))) static inline void load_pairs(const float *CARVI_RESTRICT map, const int32_t *o,
                                                                   __m256 *first, __m256 *second)
{
    __m128 a = _mm_loadh_pi(_mm_castpd_ps(_mm_load_sd((const double *)(map + o[0]))), (const __m64 *)(map + o[1]));
    __m128 b = _mm_loadh_pi(_mm_castpd_ps(_mm_load_sd((const double *)(map + o[2]))), (const __m64 *)(map + o[3]));
    __m128 c = _mm_loadh_pi(_mm_castpd_ps(_mm_load_sd((const double *)(map + o[4]))), (const __m64 *)(map + o[5]));
    __m128 d = _mm_loadh_pi(_mm_castpd_ps(_mm_load_sd((const double *)(map + o[6]))), (const __m64 *)(map + o[7]));
    __m256 ac = _mm256_insertf128_ps(_mm256_castps128_ps256(a), c, 1); /* l0 l1 | l4 l5 (pairs) */
    __m256 bd = _mm256_insertf128_ps(_mm256_castps128_ps256(b), d, 1); /* l2 l3 | l6 l7 */
    *first = _mm256_shuffle_ps(ac, bd, _MM_SHUFFLE(2, 0, 2, 0));       /* l0 l1 l2 l3 | l4 l5 l6 l7 */
    *second = _mm256_shuffle_ps(ac, bd, _MM_SHUFFLE(3, 1, 3, 1));
}

/* sample_depths with fused multiply-adds, eight depths at a time: the same arithmetic, with each
 * row's two pixels read as one 8-byte load (the east one at the last column is the next row's
 * first pixel, or the next map's, never past the maps: the caller guarantees a pixel after the
 * last map it samples; its weight is 0, and the pixel itself is used as in sample_depths). */
__attribute__((target("avx2,fma"))) static void sample_depths_avx2(const view_t *v, const geom_t *g, float cx,
                                                                   float cy, const int32_t *CARVI_RESTRICT idx,
                                                                   int m, float *CARVI_RESTRICT out)
{
    const float *CARVI_RESTRICT map = v->map;
    const int32_t Wp = (int32_t)g->Wp, Hp = (int32_t)g->Hp;
    const __m256 g0x = _mm256_set1_ps(v->g0x), g0y = _mm256_set1_ps(v->g0y), vcx = _mm256_set1_ps(cx),
                 vcy = _mm256_set1_ps(cy), one = _mm256_set1_ps(1.0f), zero = _mm256_setzero_ps(),
                 sfx = _mm256_set1_ps(g->sfx), sfy = _mm256_set1_ps(g->sfy), maxx = _mm256_set1_ps(g->maxx),
                 maxy = _mm256_set1_ps(g->maxy), scale = _mm256_set1_ps(v->scale);
    const __m256i vW = _mm256_set1_epi32(Wp), vH = _mm256_set1_epi32(Hp), ione = _mm256_set1_epi32(1);
    int i = 0;
    int32_t o[8], os[8];
    for (; i + 8 <= m; i += 8) {
        __m256 df = _mm256_cvtepi32_ps(_mm256_loadu_si256((const __m256i *)(idx + i)));
        __m256 gx = _mm256_add_ps(_mm256_mul_ps(g0x, df), vcx);
        __m256 gy = _mm256_add_ps(_mm256_mul_ps(g0y, df), vcy);
        __m256 x = _mm256_mul_ps(_mm256_add_ps(gx, one), sfx);
        __m256 y = _mm256_mul_ps(_mm256_add_ps(gy, one), sfy);
        /* x > 0 ? x : 0 (a NaN to 0), then x < max ? x : max */
        x = _mm256_blendv_ps(zero, x, _mm256_cmp_ps(x, zero, _CMP_GT_OQ));
        y = _mm256_blendv_ps(zero, y, _mm256_cmp_ps(y, zero, _CMP_GT_OQ));
        x = _mm256_blendv_ps(maxx, x, _mm256_cmp_ps(x, maxx, _CMP_LT_OQ));
        y = _mm256_blendv_ps(maxy, y, _mm256_cmp_ps(y, maxy, _CMP_LT_OQ));
        __m256i ix = _mm256_cvttps_epi32(x), iy = _mm256_cvttps_epi32(y);
        __m256 w = _mm256_sub_ps(x, _mm256_cvtepi32_ps(ix)), n = _mm256_sub_ps(y, _mm256_cvtepi32_ps(iy));
        __m256 e = _mm256_sub_ps(one, w), s = _mm256_sub_ps(one, n);
        __m256 nw = _mm256_mul_ps(s, e), ne = _mm256_mul_ps(s, w), sw = _mm256_mul_ps(n, e), se = _mm256_mul_ps(n, w);
        __m256i vo = _mm256_add_epi32(_mm256_mullo_epi32(iy, vW), ix);
        __m256i east = _mm256_cmpgt_epi32(vW, _mm256_add_epi32(ix, ione)); /* ix + 1 < Wp */
        __m256i vos = _mm256_and_si256(_mm256_cmpgt_epi32(vH, _mm256_add_epi32(iy, ione)), vW);
        _mm256_storeu_si256((__m256i *)o, vo);
        _mm256_storeu_si256((__m256i *)os, _mm256_add_epi32(vo, vos));
        __m256 t0, t1, b0, b1;
        load_pairs(map, o, &t0, &t1);
        load_pairs(map, os, &b0, &b1);
        __m256 emask = _mm256_castsi256_ps(east);
        __m256 vnw = _mm256_mul_ps(t0, scale), vne = _mm256_mul_ps(_mm256_blendv_ps(t0, t1, emask), scale);
        __m256 vsw = _mm256_mul_ps(b0, scale), vse = _mm256_mul_ps(_mm256_blendv_ps(b0, b1, emask), scale);
        __m256 r = _mm256_fmadd_ps(vse, se, _mm256_fmadd_ps(vsw, sw, _mm256_fmadd_ps(vne, ne, _mm256_mul_ps(vnw, nw))));
        _mm256_storeu_ps(out + i, r);
    }
    if (i < m)
        sample_depths(v, g, cx, cy, idx + i, m - i, out + i, 1);
}
#else
#define keep_negative_avx2(idx, cost, s, na) keep_negative(idx, cost, s, 0, 0, na)
#define sample_depths_avx2(v, g, cx, cy, idx, m, out) sample_depths(v, g, cx, cy, idx, m, out, 1)
#endif

CARVI_INLINE geom_t geometry(int64_t Hp, int64_t Wp)
{
    geom_t g = {Hp, Wp, (float)(Wp - 1) / 2, (float)(Hp - 1) / 2, (float)(Wp - 1), (float)(Hp - 1)};
    return g;
}

/* Bilinear samples of map k of ext, scaled, at m normalised coordinates xy[2 i], xy[2 i + 1] (the
 * loader's self-test against grid_sample, and the tests). Reads only inside map k. */
CARVI_INLINE void samples_at(const float *ext, int64_t Hp, int64_t Wp, int64_t k, float scale, const float *xy,
                             int64_t m, float *out, const int fused)
{
    geom_t g = geometry(Hp, Wp);
    /* as a column at depth 0 with the coordinates as its in-plane terms */
    view_t v = {ext + k * Hp * Wp, scale, 0, 0, 0, 0, 0, 0, 0, 0};
    int32_t zero = 0;
    for (int64_t i = 0; i < m; i++)
        sample_depths(&v, &g, xy[2 * i], xy[2 * i + 1], &zero, 1, out + i, fused);
}

/* Samples of map k of ext, scaled, at depths 0 .. m - 1 of one column: coordinates
 * (g0x d) + cx, (g0y d) + cy, m <= CARVI_MAX_RESOLUTION, read by the carving's own sampler
 * (the fused one may read one float past map k). */
CARVI_INLINE void line_at(const float *ext, int64_t Hp, int64_t Wp, int64_t k, float scale, float g0x, float g0y,
                          float cx, float cy, int64_t m, float *out, const int fused)
{
    geom_t g = geometry(Hp, Wp);
    view_t v = {ext + k * Hp * Wp, scale, g0x, g0y, 0, 0, 0, 0, 0, 0};
    int32_t idx[CARVI_MAX_RESOLUTION];
    if (m > CARVI_MAX_RESOLUTION)
        m = CARVI_MAX_RESOLUTION;
    for (int64_t d = 0; d < m; d++)
        idx[d] = (int32_t)d;
    if (fused)
        sample_depths_avx2(&v, &g, cx, cy, idx, (int)m, out);
    else
        sample_depths(&v, &g, cx, cy, idx, (int)m, out, 0);
}

CARVI_INLINE int carve(const float *ext, int64_t Hp, int64_t Wp, const int64_t *views, const float *scale,
                       const float *G, const float *colcost, int64_t V, int64_t n, int imprint, int64_t b0, int64_t b1,
                       uint8_t *occ, uint8_t *columns, uint8_t *nonempty, int64_t *samples, const int fused)
{
    if (V > CARVI_MAX_VIEWS || n > CARVI_MAX_RESOLUTION || n < 1)
        return -1;
    const int64_t HW = n * n;
    const geom_t g = geometry(Hp, Wp);
    view_t vw[CARVI_MAX_VIEWS];
    int order[CARVI_MAX_VIEWS];
    float cx[CARVI_MAX_VIEWS], cy[CARVI_MAX_VIEWS];
    int32_t all[CARVI_MAX_RESOLUTION], idx[CARVI_MAX_RESOLUTION];
    float cost[CARVI_MAX_RESOLUTION], s[CARVI_MAX_RESOLUTION];
    for (int64_t d = 0; d < n; d++)
        all[d] = (int32_t)d;
    for (int64_t b = b0; b < b1; b++) {
        int U = 0;
        for (int64_t j = 0; j < V; j++) {
            int64_t m = views[b * V + j];
            if (m < 0)
                continue;
            const float *gj = G + (b * V + j) * 8;
            view_t *v = &vw[U];
            v->map = ext + m * Hp * Wp;
            v->scale = scale[b * V + j];
            v->g0x = gj[0]; v->g1x = gj[1]; v->g2x = gj[2]; v->g3x = gj[3];
            v->g0y = gj[4]; v->g1y = gj[5]; v->g2y = gj[6]; v->g3y = gj[7];
            order[U] = U;
            U++;
        }
        const float *cc = colcost + b * HW;
        uint8_t *ob = occ + b * n * HW;
        int64_t count = 0;
        int any = 0;
        for (int64_t k = 0; k < HW; k++) {
            const float c0 = cc[k];
            if (!(c0 < 0.0f))
                continue; /* background column: never interior, never imprinted */
            const float hf = (float)(k / n), wf = (float)(k % n);
            for (int u = 0; u < U; u++) {
                const view_t *v = &vw[u];
                float ax = v->g1x * hf, bx = v->g2x * wf, ay = v->g1y * hf, by = v->g2y * wf;
                cx[u] = (ax + bx) + v->g3x;
                cy[u] = (ay + by) + v->g3y;
            }
            /* 1. early exit: candidates shrink view by view */
            int na = (int)n, most = -1, dropped_most = 0;
            for (int64_t d = 0; d < n; d++) {
                idx[d] = (int32_t)d;
                cost[d] = c0;
            }
            for (int r = 0; r < U && na > 0; r++) {
                const int u = order[r];
                if (fused)
                    sample_depths_avx2(&vw[u], &g, cx[u], cy[u], idx, na, s);
                else
                    sample_depths(&vw[u], &g, cx[u], cy[u], idx, na, s, 0);
                count += na;
                int m = fused ? keep_negative_avx2(idx, cost, s, na) : keep_negative(idx, cost, s, 0, 0, na);
                if (na - m > dropped_most) {
                    dropped_most = na - m;
                    most = r;
                }
                na = m;
            }
            if (most > 0) { /* the view that dropped the most goes first in the next column */
                int u = order[most];
                for (int r = most; r > 0; r--)
                    order[r] = order[r - 1];
                order[0] = u;
            }
            int inside = na > 0;
            for (int i = 0; i < na; i++)
                ob[(int64_t)idx[i] * HW + k] = 1;
            /* 2. imprinting: the first depth of minimal C, from every view at every depth */
            if (!inside && imprint) {
                for (int64_t d = 0; d < n; d++)
                    cost[d] = c0;
                for (int u = 0; u < U; u++) {
                    if (fused)
                        sample_depths_avx2(&vw[u], &g, cx[u], cy[u], all, (int)n, s);
                    else
                        sample_depths(&vw[u], &g, cx[u], cy[u], all, (int)n, s, 0);
                    for (int64_t d = 0; d < n; d++)
                        cost[d] = s[d] > cost[d] ? s[d] : cost[d];
                }
                count += U * n;
                int64_t best = 0;
                for (int64_t d = 1; d < n; d++)
                    if (cost[d] < cost[best])
                        best = d;
                ob[best * HW + k] = 1;
                inside = 1;
            }
            if (inside) {
                columns[b * HW + k] = 1;
                any = 1;
            }
        }
        nonempty[b] = (uint8_t)any;
        samples[b] = count;
    }
    return 0;
}

/* Entry points: one copy of each routine per variant, the fma one compiled for AVX2 and FMA (its
 * callers check has_fma() first: on a processor without them it would fault). */
#define CARVI_CARVE_ARGS                                                                                          \
    const float *ext, int64_t Hp, int64_t Wp, const int64_t *views, const float *scale, const float *G,          \
        const float *colcost, int64_t V, int64_t n, int imprint, int64_t b0, int64_t b1, uint8_t *occ,           \
        uint8_t *columns, uint8_t *nonempty, int64_t *samples
#define CARVI_CARVE_CALL(FUSED)                                                                                   \
    carve(ext, Hp, Wp, views, scale, G, colcost, V, n, imprint, b0, b1, occ, columns, nonempty, samples, FUSED)

static int carve_plain(CARVI_CARVE_ARGS) { return CARVI_CARVE_CALL(0); }
CARVI_FMA_TARGET static int carve_fma(CARVI_CARVE_ARGS) { return CARVI_CARVE_CALL(1); }

static void samples_plain(const float *ext, int64_t Hp, int64_t Wp, int64_t k, float scale, const float *xy,
                          int64_t m, float *out)
{
    samples_at(ext, Hp, Wp, k, scale, xy, m, out, 0);
}
CARVI_FMA_TARGET static void samples_fma(const float *ext, int64_t Hp, int64_t Wp, int64_t k, float scale,
                                         const float *xy, int64_t m, float *out)
{
    samples_at(ext, Hp, Wp, k, scale, xy, m, out, 1);
}

static void line_plain(const float *ext, int64_t Hp, int64_t Wp, int64_t k, float scale, float g0x, float g0y,
                       float cx, float cy, int64_t m, float *out)
{
    line_at(ext, Hp, Wp, k, scale, g0x, g0y, cx, cy, m, out, 0);
}
CARVI_FMA_TARGET static void line_fma(const float *ext, int64_t Hp, int64_t Wp, int64_t k, float scale, float g0x,
                                      float g0y, float cx, float cy, int64_t m, float *out)
{
    line_at(ext, Hp, Wp, k, scale, g0x, g0y, cx, cy, m, out, 1);
}

/* Whether this processor can run the fma variant. */
static int has_fma()
{
#if defined(CARVI_X86)
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
#elif defined(__aarch64__) || defined(_M_ARM64)
    return 1;
#else
    return 0;
#endif
}

} // namespace carvi
