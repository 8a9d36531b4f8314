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
 * one buffer per thread, summed at the end. With bf16 = 1, qe, out, g_out and g_qe are bfloat16 (uint16 bit
 * patterns, what bf16 autocast's batched products give and take); each query's rows are widened to float32 on load,
 * all arithmetic is float32, and results are rounded to nearest-even bf16 on store.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define SRC_ROW(ix, n, e, E) ((ix) ? (ix)[(n) * (E) + (e)] : (n) * (E) + (e))

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

void gea_forward(const void *qe, const float *src, const int64_t *idx, const float *rel, const uint8_t *mask,
                 void *out, float *w, int64_t N, int64_t H, int64_t E, int64_t Dc, int64_t Dr, int threads, int bf16) {
    const int64_t De = Dc + Dr;
#pragma omp parallel num_threads(threads)
    {
        float *ql = (float *)malloc(sizeof(float) * H * De);
        float *ol = (float *)malloc(sizeof(float) * H * De);
#pragma omp for schedule(static)
        for (int64_t n = 0; n < N; ++n) {
            const uint8_t *m = mask + n * E;
            const float *r = rel + n * E * Dr;
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
                    float l = dotf(q, src + SRC_ROW(idx, n, e, E) * Dc, Dc) + dotf(q + Dc, r + e * Dr, Dr);
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
                    axpyf(wh[e], src + SRC_ROW(idx, n, e, E) * Dc, o, Dc);
                    axpyf(wh[e], r + e * Dr, o + Dc, Dr);
                }
            }
            store_rows(out, ol, n, N, H, De, bf16);
        }
        free(ql);
        free(ol);
    }
}

void gea_backward(const void *qe, const float *src, const int64_t *idx, const float *rel, const uint8_t *mask,
                  const float *w, const void *g_out, void *g_qe, float *g_src, float *g_rel, int64_t N, int64_t Ns,
                  int64_t H, int64_t E, int64_t Dc, int64_t Dr, int threads, int bf16) {
    const int64_t De = Dc + Dr;
    const int scatter = idx != NULL;
    if (threads < 1) threads = 1;
    float **bufs = (float **)calloc((size_t)threads, sizeof(float *));
    bufs[0] = g_src;  /* zero-filled by the caller when scattering */
    for (int t = 1; t < threads && scatter; ++t) bufs[t] = (float *)calloc((size_t)(Ns * Dc), sizeof(float));
#pragma omp parallel num_threads(threads)
    {
        int tid = 0;
#ifdef _OPENMP
        tid = omp_get_thread_num();
#endif
        float *gs = scatter ? bufs[tid] : g_src;
        float *gl = (float *)malloc(sizeof(float) * H * E);
        float *gk = (float *)malloc(sizeof(float) * De);
        float *ql = (float *)malloc(sizeof(float) * H * De);
        float *gol = (float *)malloc(sizeof(float) * H * De);
        float *gql = (float *)malloc(sizeof(float) * H * De);
#pragma omp for schedule(static)
        for (int64_t n = 0; n < N; ++n) {
            const uint8_t *m = mask + n * E;
            const float *r = rel + n * E * Dr;
            const float *wn = w + n * H * E;
            float *gr = g_rel + n * E * Dr;
            load_rows(ql, qe, n, N, H, De, bf16);
            load_rows(gol, g_out, n, N, H, De, bf16);
            memset(gql, 0, sizeof(float) * H * De);
            memset(gr, 0, sizeof(float) * E * Dr);
            if (!scatter) memset(g_src + n * E * Dc, 0, sizeof(float) * E * Dc);
            for (int64_t h = 0; h < H; ++h) {
                const float *g = gol + h * De;
                const float *wh = wn + h * E;
                float *glh = gl + h * E;
                float *gqh = gql + h * De;
                float s = 0.f;
                for (int64_t e = 0; e < E; ++e) {
                    if (!m[e] || wh[e] == 0.f) { glh[e] = 0.f; continue; }
                    float gw = dotf(g, src + SRC_ROW(idx, n, e, E) * Dc, Dc) + dotf(g + Dc, r + e * Dr, Dr);
                    glh[e] = gw;
                    s += wh[e] * gw;
                }
                for (int64_t e = 0; e < E; ++e) {
                    if (!m[e] || wh[e] == 0.f) continue;
                    glh[e] = wh[e] * (glh[e] - s);
                    axpyf(glh[e], src + SRC_ROW(idx, n, e, E) * Dc, gqh, Dc);
                    axpyf(glh[e], r + e * Dr, gqh + Dc, Dr);
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
                axpyf(1.f, gk, gs + SRC_ROW(idx, n, e, E) * Dc, Dc);
                memcpy(gr + e * Dr, gk + Dc, sizeof(float) * Dr);
            }
        }
        free(gl);
        free(gk);
        free(ql);
        free(gol);
        free(gql);
    }
    for (int t = 1; t < threads && scatter; ++t) {
        float *b = bufs[t];
#pragma omp parallel for num_threads(threads) schedule(static)
        for (int64_t i = 0; i < Ns * Dc; ++i) g_src[i] += b[i];
        free(b);
    }
    free(bufs);
}
