/* Residual add with inverted dropout, y = x + keep(i) * u * scale, whose keep mask is a hash of (seed, i) instead of
 * a stored random tensor: the CPU kernel of r1sim_sumo/model/residual_dropout.py.
 *
 * keep(i): element i's 16-bit lane (i % 4) of splitmix64(seed + (i / 4) * golden) is >= thr (thr = round(p * 65536)), so one
 * 64-bit hash decides four elements, any element's decision depends on (seed, i) only (the same for any number of
 * threads and recomputed in the backward instead of saved), and the drop probability is thr / 65536.
 * x, y, g_x: float32; u and g_u: float32, or bfloat16 (uint16 bit patterns; what bf16 autocast's linear layers give)
 * when u_bf16 = 1. Arithmetic is float32, bf16 stores round to nearest even.
 */
#include <stdint.h>
#include <string.h>

static inline uint64_t mix64(uint64_t z) {
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
    return z ^ (z >> 31);
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

#define CHUNK 2048 /* elements per mask chunk (a multiple of 4): the mask is made, then used, in L1 */

/* f[k] = keep factor (0 or scale) of element i0 + k, k < CHUNK; i0 a multiple of 4 */
static inline void chunk_factors(uint64_t seed, int64_t i0, uint32_t thr, float scale, float *restrict f) {
    const uint64_t b0 = (uint64_t)(i0 / 4);
#pragma omp simd
    for (int64_t b = 0; b < CHUNK / 4; ++b) {
        const uint64_t h = mix64(seed + (b0 + (uint64_t)b) * 0x9e3779b97f4a7c15ULL);
        f[4 * b + 0] = (uint32_t)(h & 0xffffu) >= thr ? scale : 0.f;
        f[4 * b + 1] = (uint32_t)((h >> 16) & 0xffffu) >= thr ? scale : 0.f;
        f[4 * b + 2] = (uint32_t)((h >> 32) & 0xffffu) >= thr ? scale : 0.f;
        f[4 * b + 3] = (uint32_t)(h >> 48) >= thr ? scale : 0.f;
    }
}

void rdrop_forward(const float *x, const void *u, float *y, int64_t n, uint64_t seed, uint32_t thr, float scale,
                   int u_bf16, int threads) {
    const int64_t nc = (n + CHUNK - 1) / CHUNK;
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t c = 0; c < nc; ++c) {
        float f[CHUNK];
        const int64_t i0 = c * CHUNK, m = n - i0 < CHUNK ? n - i0 : CHUNK;
        chunk_factors(seed, i0, thr, scale, f);
        const float *restrict xc = x + i0;
        float *restrict yc = y + i0;
        if (u_bf16) {
            const uint16_t *restrict uc = (const uint16_t *)u + i0;
#pragma omp simd
            for (int64_t k = 0; k < m; ++k) yc[k] = xc[k] + f[k] * bf16_to_f(uc[k]);
        } else {
            const float *restrict uc = (const float *)u + i0;
#pragma omp simd
            for (int64_t k = 0; k < m; ++k) yc[k] = xc[k] + f[k] * uc[k];
        }
    }
}

void rdrop_backward(const float *g, void *g_u, int64_t n, uint64_t seed, uint32_t thr, float scale, int u_bf16,
                    int threads) {
    const int64_t nc = (n + CHUNK - 1) / CHUNK;
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t c = 0; c < nc; ++c) {
        float f[CHUNK];
        const int64_t i0 = c * CHUNK, m = n - i0 < CHUNK ? n - i0 : CHUNK;
        chunk_factors(seed, i0, thr, scale, f);
        const float *restrict gc = g + i0;
        if (u_bf16) {
            uint16_t *restrict oc = (uint16_t *)g_u + i0;
#pragma omp simd
            for (int64_t k = 0; k < m; ++k) oc[k] = f_to_bf16(f[k] * gc[k]);
        } else {
            float *restrict oc = (float *)g_u + i0;
#pragma omp simd
            for (int64_t k = 0; k < m; ++k) oc[k] = f[k] * gc[k];
        }
    }
}
