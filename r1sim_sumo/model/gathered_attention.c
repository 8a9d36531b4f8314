/* Attention of each query over its own few edges, with the edge features' content part gathered from a source
 * table on the fly instead of materialised per edge: the CPU kernel of r1sim_sumo/model/gathered_attention.py.
 *
 * An edge (n, e) has the feature vector k = [src[idx[n, e]] (Dc floats), rel[n, e] (Dr floats)], De = Dc + Dr.
 * Forward, for every query n and head h:
 *     logit[h, e] = qe[n, h, :] . k(n, e)            (masked edges excluded)
 *     w[n, h, :]  = softmax over the valid edges (all zero when no edge is valid)
 *     out[n, h, :] = sum_e w[n, h, e] k(n, e)
 * Backward (g = dL/d out): g_w = g . k; g_logit = w (g_w - sum_e w g_w);
 *     g_qe[n, h] = sum_e g_logit[h, e] k(n, e);  g_k(n, e) = sum_h g_logit[h, e] qe[n, h] + w[n, h, e] g[n, h];
 *     g_rel[n, e] = g_k[Dc:];  g_src[idx[n, e]] += g_k[:Dc].
 * Layouts: qe, out, g_out, g_qe are head-major [H, N, De] (what a per-head batched product with the key / value
 * maps gives and takes without a transpose); w is [N, H, E]; src [Ns, Dc]; rel, g_rel [N, E, Dr]. All contiguous
 * float32 (idx int64, mask one byte per edge). idx == NULL means the identity: edge (n, e) reads src row n * E + e
 * (per-edge content, e.g. map tokens with the signal state of the query's step), and g_src is then written
 * directly (Ns = N * E, every row). Queries are split over `threads` OpenMP threads; the scatter into g_src goes to
 * one buffer per thread, summed at the end. `flags` says which tensors are bfloat16 (uint16 bit patterns, what bf16
 * autocast's products give and take) instead of float32: BF16_QE (qe, out, g_out, g_qe), BF16_SRC (src and g_src),
 * BF16_REL (rel and g_rel). Values are widened to float32 on load, all arithmetic is float32, and results are
 * rounded to nearest-even bf16 on store; a bf16 g_src under a scatter is summed in float32 buffers first.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define SRC_ROW(ix, n, e, E) ((ix) ? (ix)[(n) * (E) + (e)] : (n) * (E) + (e))
#define BF16_QE 1
#define BF16_SRC 2
#define BF16_REL 4

static inline float dotf(const float *restrict a, const float *restrict b, int64_t n) {
    float s = 0.f;
#pragma omp simd reduction(+ : s)
    for (int64_t i = 0; i < n; ++i) s += a[i] * b[i];
    return s;
}

static inline void axpyf(float a, const float *restrict x, float *restrict y, int64_t n) {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) y[i] += a * x[i];
}

static inline float bf16_to_f(uint16_t h) {
    uint32_t u = (uint32_t)h << 16;
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

static inline uint16_t f_to_bf16(float f) {
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    if ((u & 0x7fffffffu) > 0x7f800000u) return (uint16_t)((u >> 16) | 0x40u); /* NaN stays NaN */
    u += 0x7fffu + ((u >> 16) & 1u);
    return (uint16_t)(u >> 16);
}

/* a . b[off : off + n] with b float32 or bf16 */
static inline float dot_any(const float *restrict a, const void *b, int64_t off, int64_t n, int bf) {
    if (!bf) return dotf(a, (const float *)b + off, n);
    const uint16_t *restrict p = (const uint16_t *)b + off;
    float s = 0.f;
#pragma omp simd reduction(+ : s)
    for (int64_t i = 0; i < n; ++i) s += a[i] * bf16_to_f(p[i]);
    return s;
}

/* y += a x[off : off + n] with x float32 or bf16 */
static inline void axpy_any(float a, const void *x, int64_t off, float *restrict y, int64_t n, int bf) {
    if (!bf) { axpyf(a, (const float *)x + off, y, n); return; }
    const uint16_t *restrict p = (const uint16_t *)x + off;
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) y[i] += a * bf16_to_f(p[i]);
}

/* t[off : off + n] = v (float32 or bf16) */
static inline void store_any(void *t, int64_t off, const float *restrict v, int64_t n, int bf) {
    if (!bf) { memcpy((float *)t + off, v, sizeof(float) * n); return; }
    uint16_t *restrict p = (uint16_t *)t + off;
    for (int64_t i = 0; i < n; ++i) p[i] = f_to_bf16(v[i]);
}

/* rows (h * N + n) of a head-major [H, N, De] tensor -> dst [H, De] (float32) */
static inline void load_rows(float *dst, const void *t, int64_t n, int64_t N, int64_t H, int64_t De, int bf16) {
    for (int64_t h = 0; h < H; ++h) {
        if (bf16) {
            const uint16_t *r = (const uint16_t *)t + (h * N + n) * De;
            for (int64_t i = 0; i < De; ++i) dst[h * De + i] = bf16_to_f(r[i]);
        } else {
            memcpy(dst + h * De, (const float *)t + (h * N + n) * De, sizeof(float) * De);
        }
    }
}

static inline void store_rows(void *t, const float *src, int64_t n, int64_t N, int64_t H, int64_t De, int bf16) {
    for (int64_t h = 0; h < H; ++h) {
        if (bf16) {
            uint16_t *r = (uint16_t *)t + (h * N + n) * De;
            for (int64_t i = 0; i < De; ++i) r[i] = f_to_bf16(src[h * De + i]);
        } else {
            memcpy((float *)t + (h * N + n) * De, src + h * De, sizeof(float) * De);
        }
    }
}

void gea_forward(const void *qe, const void *src, const int64_t *idx, const void *rel, const uint8_t *mask,
                 void *out, float *w, int64_t N, int64_t H, int64_t E, int64_t Dc, int64_t Dr, int threads, int flags) {
    const int64_t De = Dc + Dr;
    const int bf16 = flags & BF16_QE, sbf = flags & BF16_SRC, rbf = flags & BF16_REL;
#pragma omp parallel num_threads(threads)
    {
        float *ql = (float *)malloc(sizeof(float) * H * De);
        float *ol = (float *)malloc(sizeof(float) * H * De);
#pragma omp for schedule(static)
        for (int64_t n = 0; n < N; ++n) {
            const uint8_t *m = mask + n * E;
            const int64_t r0 = n * E * Dr;  /* offset of the query's first rel row */
            float *wn = w + n * H * E;
            load_rows(ql, qe, n, N, H, De, bf16);
            memset(ol, 0, sizeof(float) * H * De);
            for (int64_t h = 0; h < H; ++h) {
                const float *q = ql + h * De;
                float *o = ol + h * De;
                float *wh = wn + h * E;
                float mx = -INFINITY;
                for (int64_t e = 0; e < E; ++e) {
                    if (!m[e]) { wh[e] = 0.f; continue; }
                    float l = dot_any(q, src, SRC_ROW(idx, n, e, E) * Dc, Dc, sbf) + dot_any(q + Dc, rel, r0 + e * Dr, Dr, rbf);
                    wh[e] = l;
                    if (l > mx) mx = l;
                }
                if (mx == -INFINITY) continue;  /* no valid edge: zero weights, zero output */
                float z = 0.f;
                for (int64_t e = 0; e < E; ++e) {
                    if (!m[e]) continue;
                    wh[e] = expf(wh[e] - mx);
                    z += wh[e];
                }
                const float inv = 1.f / z;
                for (int64_t e = 0; e < E; ++e) {
                    if (!m[e]) continue;
                    wh[e] *= inv;
                    axpy_any(wh[e], src, SRC_ROW(idx, n, e, E) * Dc, o, Dc, sbf);
                    axpy_any(wh[e], rel, r0 + e * Dr, o + Dc, Dr, rbf);
                }
            }
            store_rows(out, ol, n, N, H, De, bf16);
        }
        free(ql);
        free(ol);
    }
}

void gea_backward(const void *qe, const void *src, const int64_t *idx, const void *rel, const uint8_t *mask,
                  const float *w, const void *g_out, void *g_qe, void *g_src, void *g_rel, int64_t N, int64_t Ns,
                  int64_t H, int64_t E, int64_t Dc, int64_t Dr, int threads, int flags) {
    const int64_t De = Dc + Dr;
    const int bf16 = flags & BF16_QE, sbf = flags & BF16_SRC, rbf = flags & BF16_REL;
    const size_t rsz = rbf ? sizeof(uint16_t) : sizeof(float), ssz = sbf ? sizeof(uint16_t) : sizeof(float);
    const int scatter = idx != NULL;
    if (threads < 1) threads = 1;
    float **bufs = (float **)calloc((size_t)threads, sizeof(float *));
    /* float32 g_src under a scatter: zero-filled by the caller and accumulated in place; bf16: in float32 buffers */
    bufs[0] = scatter && sbf ? (float *)calloc((size_t)(Ns * Dc), sizeof(float)) : (float *)g_src;
    for (int t = 1; t < threads && scatter; ++t) bufs[t] = (float *)calloc((size_t)(Ns * Dc), sizeof(float));
#pragma omp parallel num_threads(threads)
    {
        int tid = 0;
#ifdef _OPENMP
        tid = omp_get_thread_num();
#endif
        float *gs = scatter ? bufs[tid] : NULL;
        float *gl = (float *)malloc(sizeof(float) * H * E);
        float *gk = (float *)malloc(sizeof(float) * De);
        float *ql = (float *)malloc(sizeof(float) * H * De);
        float *gol = (float *)malloc(sizeof(float) * H * De);
        float *gql = (float *)malloc(sizeof(float) * H * De);
#pragma omp for schedule(static)
        for (int64_t n = 0; n < N; ++n) {
            const uint8_t *m = mask + n * E;
            const int64_t r0 = n * E * Dr;  /* offset of the query's first rel row */
            const float *wn = w + n * H * E;
            load_rows(ql, qe, n, N, H, De, bf16);
            load_rows(gol, g_out, n, N, H, De, bf16);
            memset(gql, 0, sizeof(float) * H * De);
            memset((char *)g_rel + r0 * rsz, 0, rsz * E * Dr);  /* bf16 zero is all-zero bits too */
            if (!scatter) memset((char *)g_src + n * E * Dc * ssz, 0, ssz * E * Dc);
            for (int64_t h = 0; h < H; ++h) {
                const float *g = gol + h * De;
                const float *wh = wn + h * E;
                float *glh = gl + h * E;
                float *gqh = gql + h * De;
                float s = 0.f;
                for (int64_t e = 0; e < E; ++e) {
                    if (!m[e] || wh[e] == 0.f) { glh[e] = 0.f; continue; }
                    float gw = dot_any(g, src, SRC_ROW(idx, n, e, E) * Dc, Dc, sbf) + dot_any(g + Dc, rel, r0 + e * Dr, Dr, rbf);
                    glh[e] = gw;
                    s += wh[e] * gw;
                }
                for (int64_t e = 0; e < E; ++e) {
                    if (!m[e] || wh[e] == 0.f) continue;
                    glh[e] = wh[e] * (glh[e] - s);
                    axpy_any(glh[e], src, SRC_ROW(idx, n, e, E) * Dc, gqh, Dc, sbf);
                    axpy_any(glh[e], rel, r0 + e * Dr, gqh + Dc, Dr, rbf);
                }
            }
            store_rows(g_qe, gql, n, N, H, De, bf16);
            for (int64_t e = 0; e < E; ++e) {
                if (!m[e]) continue;
                memset(gk, 0, sizeof(float) * De);
                int any = 0;
                for (int64_t h = 0; h < H; ++h) {
                    const float we = wn[h * E + e];
                    if (we == 0.f) continue;
                    any = 1;
                    axpyf(gl[h * E + e], ql + h * De, gk, De);
                    axpyf(we, gol + h * De, gk, De);
                }
                if (!any) continue;
                if (scatter) axpyf(1.f, gk, gs + idx[n * E + e] * Dc, Dc);
                else store_any(g_src, (n * E + e) * Dc, gk, Dc, sbf);
                store_any(g_rel, r0 + e * Dr, gk + Dc, Dr, rbf);
            }
        }
        free(gl);
        free(gk);
        free(ql);
        free(gol);
        free(gql);
    }
    if (scatter && (threads > 1 || sbf)) {
        float *acc = bufs[0];
#pragma omp parallel for num_threads(threads) schedule(static)
        for (int64_t i = 0; i < Ns * Dc; ++i) {
            float v = acc[i];
            for (int t = 1; t < threads; ++t) v += bufs[t][i];
            if (sbf) ((uint16_t *)g_src)[i] = f_to_bf16(v);
            else acc[i] = v;
        }
        for (int t = 1; t < threads; ++t) free(bufs[t]);
        if (sbf) free(bufs[0]);
    }
    free(bufs);
}
