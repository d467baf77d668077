// Fused attention for many short sequences of narrow heads: GRaF's inference on a CPU (graf.models.graf.kernels).
// Compiled at first use by graf.models.graf.kernels.native (c++ -O3 -march=native), called through ctypes.
// 16 queries at a time in one vector: their scores against every key, the row maximum, exp and the
// value-weighted sums, all in registers; nothing of size queries x keys is written to memory.
#include <cmath>
#include <cstdint>
#include <cstring>
#include <utility>
#include <vector>

// A vector is one register of the widest kind the CPU has for floats: 16 lanes with AVX-512, 8 with AVX2, where a
// 16-lane vector is split in two and the kernels' register arrays spill to memory (GRaF's training step 2.1x and its
// inference 2.2x slower on a 2-core AVX2 EPYC).  Every lane is a query, key or ray of its own and nothing is summed
// across lanes; the width changes which multiply-adds the compiler fuses, so the last bits of a result (not its
// figures: docs/reproducibility.md).  GRAF_KERNEL_VECTOR_BYTES=64 (graf.models.graf.kernels.native) builds the
// 16-lane kernel anywhere, as before.
#ifndef GRAF_VECTOR_BYTES
#if defined(__AVX2__) && !defined(__AVX512F__)
#define GRAF_VECTOR_BYTES 32
#else
#define GRAF_VECTOR_BYTES 64
#endif
#endif
typedef float vf __attribute__((vector_size(GRAF_VECTOR_BYTES)));
typedef int32_t vi __attribute__((vector_size(GRAF_VECTOR_BYTES)));
static const int LANES = GRAF_VECTOR_BYTES / 4;
static const int MAX_DIM = 64;
static const int MAX_KEYS = 4096;

static inline vf splat(float x) { vf v = {}; return v + x; }

// exp(x) for x <= 0 (the row maximum is subtracted first): Cephes' range reduction and degree-6 polynomial
// (relative error about 2e-7); below -87.3 the result is 0.
static inline vf vexp(vf x) {
    vf lo = splat(-87.3f);
    vf xc = x < lo ? lo : x;
    vf n = (xc * 1.44269504088896341f + 12582912.0f) - 12582912.0f;  // round to nearest
    vf r = xc - n * 0.693359375f;
    r = r + n * 2.12194440e-4f;
    vf p = splat(1.9875691500e-4f);
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    vi e = (__builtin_convertvector(n, vi) + 127) << 23;
    return p * (vf)e;  // below -87.3: exp(-87.3) ~ 1e-38, nothing beside a softmax's maximum term of 1
}

// 2^x for x <= 0 (the whole blocks' scores are in base 2: log2(e) is folded into their query weights): the
// nearest integer n split off exactly, 2^(x - n) by its Taylor series in (x - n) ln 2 to degree 7 (truncation
// below 1e-8 relative); below -126 the result is 2^-126.
static inline vf vexp2(vf x) {
    vf lo = splat(-126.0f);
    vf xc = x < lo ? lo : x;
    vf n = (xc + 12582912.0f) - 12582912.0f;  // round to nearest
    vf r = xc - n;                             // [-0.5, 0.5], exact
    vf p = splat(1.5252733804059840e-05f);
    p = p * r + 1.5403530393381606e-04f;
    p = p * r + 1.3333558146428443e-03f;
    p = p * r + 9.6181291076284772e-03f;
    p = p * r + 5.5504108664821580e-02f;
    p = p * r + 2.4022650695910071e-01f;
    p = p * r + 6.9314718055994531e-01f;
    p = p * r + 1.0f;
    vi e = (__builtin_convertvector(n, vi) + 127) << 23;
    return p * (vf)e;
}

static inline vf load_lanes(const float *p, int64_t nl) {
    if (nl == LANES) {
        vf v;
        std::memcpy(&v, p, sizeof v);
        return v;
    }
    float tmp[LANES] = {0};
    std::memcpy(tmp, p, nl * sizeof(float));
    vf v;
    std::memcpy(&v, tmp, sizeof v);
    return v;
}

static inline void store_lanes(float *p, vf v, int64_t nl) {
    float tmp[LANES];
    std::memcpy(tmp, &v, sizeof tmp);
    std::memcpy(p, tmp, nl * sizeof(float));
}

// sum_k a[k] * w[k * stride] + init over n terms, in four independent chains (the multiply-adds of one chain
// wait for each other; four keep the vector units busy)
static inline vf dot(const vf *a, const float *w, int64_t n, vf init, int64_t stride = 1) {
    vf s0 = init, s1 = splat(0.0f), s2 = splat(0.0f), s3 = splat(0.0f);
    const vf *end4 = a + (n & ~(int64_t)3), *end = a + n;
    for (; a < end4; a += 4, w += 4 * stride) {
        s0 += a[0] * w[0];
        s1 += a[1] * w[stride];
        s2 += a[2] * w[2 * stride];
        s3 += a[3] * w[3 * stride];
    }
    for (; a < end; a++, w += stride) s0 += a[0] * w[0];
    return (s0 + s1) + (s2 + s3);
}

// One vector of 16 queries (q [Dk]) attends to L keys: key j's feature e at k[e * stride + j], its value's feature
// e at v[e * stride + j]; out [Dv] = the softmax-weighted sum of the values (keys with mask[j] == 0 left out).
// BASE2: the scores are in base 2 (log2 e folded into the queries).
template <bool BASE2>
static inline void attend_one(const vf *q, int64_t Dk, const float *k, const float *v, int64_t Dv, int64_t stride,
                              int64_t L, const uint8_t *mask, vf *out) {
    static thread_local vf s[MAX_KEYS];
    vf mx = splat(-INFINITY);
    for (int64_t j = 0; j < L; j++) {
        if (mask && !mask[j]) continue;
        vf acc = dot(q, k + j, Dk, splat(0.0f), stride);
        s[j] = acc;
        mx = acc > mx ? acc : mx;
    }
    for (int64_t e = 0; e < Dv; e++) out[e] = splat(0.0f);
    vf sum = splat(0.0f);
    for (int64_t j = 0; j < L; j++) {
        if (mask && !mask[j]) continue;
        vf p = BASE2 ? vexp2(s[j] - mx) : vexp(s[j] - mx);
        sum += p;
        for (int64_t e = 0; e < Dv; e++) out[e] += p * v[e * stride + j];
    }
    for (int64_t e = 0; e < Dv; e++) out[e] = out[e] / sum;
}

extern "C" int graf_attention_max_dim() { return MAX_DIM; }
extern "C" int graf_attention_max_keys() { return MAX_KEYS; }

// For each batch entry b in [b0, b1): queries q [Dk, Sq], keys k [Dk, Sk], values v [Dv, Sk] (feature-major:
// row d holds feature d of every position, row stride = the sequence length), optional key mask [Sk] (nonzero
// = attend; at least one per entry), output o [Dv, Sq] = (softmax(q^T k) v^T)^T.  Entry b's arrays start at
// b times the given strides (elements).
extern "C" void graf_attention(const float *q, const float *k, const float *v, const uint8_t *mask, float *o,
                               int64_t b0, int64_t b1, int64_t Dk, int64_t Dv, int64_t Sq, int64_t Sk,
                               int64_t q_stride, int64_t k_stride, int64_t v_stride, int64_t mask_stride,
                               int64_t o_stride) {
    for (int64_t b = b0; b < b1; b++) {
        const float *qb = q + b * q_stride, *kb = k + b * k_stride, *vb = v + b * v_stride;
        const uint8_t *mb = mask ? mask + b * mask_stride : nullptr;
        float *ob = o + b * o_stride;
        for (int64_t i0 = 0; i0 < Sq; i0 += LANES) {
            const int64_t nl = Sq - i0 < LANES ? Sq - i0 : LANES;
            vf qv[MAX_DIM], out[MAX_DIM];
            for (int64_t d = 0; d < Dk; d++) qv[d] = load_lanes(qb + d * Sq + i0, nl);
            attend_one<false>(qv, Dk, kb, vb, Dv, Sk, Sk, mb, out);
            for (int64_t d = 0; d < Dv; d++) store_lanes(ob + d * Sq + i0, out[d], nl);
        }
    }
}

// ------------------------------------------------------------------------------------------------ whole blocks
// One post-norm Transformer block (graf.models.graf.attention._PostNormBlock) fused:
//   y = LN1(x + Wo Attention(Wq x, Wk c, Wv c) + bo);  out = LN2(y + W2 relu(W1 y + b1) + b2)
// over feature-major entries (x [d, S] per entry: row c holds channel c of every position), 16 positions per
// vector.  c is x itself (self-attention) or the entry's context [d, L] (cross-attention; a context stride of
// 0 shares one context among all entries, its keys and values computed once).
struct BlockWeights {
    const float *wq, *bq;    // [H*Dh, d], [H*Dh]: the query projection, log2(e)/sqrt(Dh) folded in (base-2 scores)
    const float *wkv, *bkv;  // [H*2*Dh, d], [H*2*Dh]: rows (head, key | value, Dh)
    const float *wo, *bo;    // [d, H*Dh], [d]
    const float *g1, *be1;   // LayerNorm 1 [d]
    const float *w1, *b1;    // [F, d], [F]
    const float *w2, *b2;    // [d, F], [d]
    const float *g2, *be2;   // LayerNorm 2 [d]
    float eps1, eps2;
    int64_t d, H, Dh, F;
};

static const int MAX_MODEL = 64;   // d
static const int MAX_INNER = 256;  // H * Dh and F

extern "C" int graf_block_limits(int which) { return which == 0 ? MAX_MODEL : MAX_INNER; }

static inline void layer_norm(vf *x, int64_t d, const float *g, const float *b, float eps) {
    vf mean = splat(0.0f), var = splat(0.0f);
    for (int64_t c = 0; c < d; c++) mean += x[c];
    mean = mean / (float)d;
    for (int64_t c = 0; c < d; c++) {
        vf t = x[c] - mean;
        var += t * t;
    }
    var = var / (float)d;
    float tmp[LANES];
    std::memcpy(tmp, &var, sizeof tmp);
    for (int l = 0; l < LANES; l++) tmp[l] = 1.0f / std::sqrt(tmp[l] + eps);
    vf inv;
    std::memcpy(&inv, tmp, sizeof inv);
    for (int64_t c = 0; c < d; c++) x[c] = (x[c] - mean) * inv * g[c] + b[c];
}

// Sizes known at compile time for the common blocks (D, DH, FF; 0 = read from the weights at run time): the
// compiler then unrolls the short loops and keeps the vectors in registers.
#define SIZE(K, runtime) ((K) ? (int64_t)(K) : (int64_t)(runtime))

// keys and values of one entry's context: kv [H*2*Dh][Lp] (Lp: L rounded up to whole vectors)
template <int D, int DH, int FF>
static void keys_values(const BlockWeights *w, const float *c, int64_t L, int64_t Lp, float *kv) {
    const int64_t d = SIZE(D, w->d), R = 2 * w->H * SIZE(DH, w->Dh);
    for (int64_t j0 = 0; j0 < L; j0 += LANES) {
        const int64_t nl = L - j0 < LANES ? L - j0 : LANES;
        vf cv[MAX_MODEL];
        for (int64_t k = 0; k < d; k++) cv[k] = load_lanes(c + k * L + j0, nl);
        for (int64_t r = 0; r < R; r++) {
            vf acc = dot(cv, w->wkv + r * d, d, splat(w->bkv[r]));
            std::memcpy(kv + r * Lp + j0, &acc, sizeof acc);
        }
    }
}

// 16 query positions (their inputs xv [d]) through the whole block; the result back into xv
template <int D, int DH, int FF>
static void block_lanes(const BlockWeights *w, vf *xv, const float *kv, int64_t L, int64_t Lp, const uint8_t *mask) {
    const int64_t d = SIZE(D, w->d), H = w->H, Dh = SIZE(DH, w->Dh), F = SIZE(FF, w->F), HD = H * Dh;
    vf q[MAX_INNER], o[MAX_INNER];
    for (int64_t r = 0; r < HD; r++) {
        q[r] = dot(xv, w->wq + r * d, d, splat(w->bq[r]));
    }
    for (int64_t h = 0; h < H; h++) {
        const float *kh = kv + (h * 2 * Dh) * Lp;
        attend_one<true>(q + h * Dh, Dh, kh, kh + Dh * Lp, Dh, Lp, L, mask, o + h * Dh);
    }
    vf y[MAX_MODEL], hdn[MAX_INNER];
    for (int64_t c = 0; c < d; c++) {
        y[c] = dot(o, w->wo + c * HD, HD, splat(w->bo[c]) + xv[c]);
    }
    layer_norm(y, d, w->g1, w->be1, w->eps1);
    for (int64_t f = 0; f < F; f++) {
        vf acc = dot(y, w->w1 + f * d, d, splat(w->b1[f]));
        hdn[f] = acc > 0.0f ? acc : splat(0.0f);
    }
    for (int64_t c = 0; c < d; c++) {
        xv[c] = dot(hdn, w->w2 + c * F, F, splat(w->b2[c]) + y[c]);
    }
    layer_norm(xv, d, w->g2, w->be2, w->eps2);
}

template <int D, int DH, int FF>
static void block_entries(const BlockWeights *w, const float *x, int64_t x_stride, float *y, int64_t y_stride,
                          int64_t e0, int64_t e1, int64_t S, const float *ctx, int64_t ctx_stride, int64_t L,
                          const uint8_t *mask, int64_t mask_stride) {
    const int64_t d = SIZE(D, w->d);
    const int64_t keys = ctx ? L : S, Lp = (keys + LANES - 1) / LANES * LANES;
    static thread_local std::vector<float> kv;
    kv.resize((size_t)(2 * w->H * w->Dh * Lp));
    for (int64_t e = e0; e < e1; e++) {
        const float *xe = x + e * x_stride;
        if (!ctx) {
            keys_values<D, DH, FF>(w, xe, S, Lp, kv.data());
        } else if (ctx_stride != 0 || e == e0) {
            keys_values<D, DH, FF>(w, ctx + e * ctx_stride, L, Lp, kv.data());
        }
        const uint8_t *me = mask ? mask + e * mask_stride : nullptr;
        float *ye = y + e * y_stride;
        for (int64_t i0 = 0; i0 < S; i0 += LANES) {
            const int64_t nl = S - i0 < LANES ? S - i0 : LANES;
            vf xv[MAX_MODEL];
            for (int64_t c = 0; c < d; c++) xv[c] = load_lanes(xe + c * S + i0, nl);
            block_lanes<D, DH, FF>(w, xv, kv.data(), keys, Lp, me);
            for (int64_t c = 0; c < d; c++) store_lanes(ye + c * S + i0, xv[c], nl);
        }
    }
}

// Entries [e0, e1) of x [n][d][S] (entry stride x_stride) -> y (same layout, y_stride).  ctx: null for
// self-attention, else [n][d][L] (ctx_stride; 0: one context for all); mask [n][keys] (mask_stride; 0: shared).
extern "C" void graf_block(const BlockWeights *w, const float *x, int64_t x_stride, float *y, int64_t y_stride,
                           int64_t e0, int64_t e1, int64_t S, const float *ctx, int64_t ctx_stride, int64_t L,
                           const uint8_t *mask, int64_t mask_stride) {
    if (w->d == 16 && w->Dh == 8 && w->F == 64)  // GRaF's ray transformer (10 heads of 8)
        block_entries<16, 8, 64>(w, x, x_stride, y, y_stride, e0, e1, S, ctx, ctx_stride, L, mask, mask_stride);
    else if (w->d == 16 && w->Dh == 16 && w->F == 64)  // GRaF's scene blocks (1 head of 16)
        block_entries<16, 16, 64>(w, x, x_stride, y, y_stride, e0, e1, S, ctx, ctx_stride, L, mask, mask_stride);
    else
        block_entries<0, 0, 0>(w, x, x_stride, y, y_stride, e0, e1, S, ctx, ctx_stride, L, mask, mask_stride);
}

// ------------------------------------------------------------------------------------------------ MLP2
// GRaF's MLP2 between the scene blocks and the ray transformer, fused with the voxels' distance code:
//   y = W2 relu(W1 x + b1) + b2 + code^T
// over feature-major entries (x, y [d, S] per entry), 16 positions per vector; code (optional) is token-major
// [n][S][d] (entry e's position i at code + (e * S + i) * d).  The hidden layer never leaves the registers.
template <int D, int M>
static void mlp_entries(const float *w1, const float *b1, const float *w2, const float *b2, int64_t d_rt,
                        int64_t m_rt, const float *x, int64_t x_stride, const float *code, float *y, int64_t y_stride,
                        int64_t e0, int64_t e1, int64_t S) {
    const int64_t d = SIZE(D, d_rt), m = SIZE(M, m_rt);
    for (int64_t e = e0; e < e1; e++) {
        const float *xe = x + e * x_stride;
        float *ye = y + e * y_stride;
        for (int64_t i0 = 0; i0 < S; i0 += LANES) {
            const int64_t nl = S - i0 < LANES ? S - i0 : LANES;
            vf xv[MAX_MODEL], hdn[MAX_INNER], init[MAX_MODEL];
            for (int64_t c = 0; c < d; c++) xv[c] = load_lanes(xe + c * S + i0, nl);
            if (code) {
                float tmp[MAX_MODEL][LANES] = {};
                const float *ce = code + (e * S + i0) * d;
                for (int64_t l = 0; l < nl; l++)
                    for (int64_t c = 0; c < d; c++) tmp[c][l] = ce[l * d + c];
                for (int64_t c = 0; c < d; c++) std::memcpy(&init[c], tmp[c], sizeof(vf));
            } else {
                for (int64_t c = 0; c < d; c++) init[c] = splat(0.0f);
            }
            for (int64_t f = 0; f < m; f++) {
                vf acc = dot(xv, w1 + f * d, d, splat(b1[f]));
                hdn[f] = acc > 0.0f ? acc : splat(0.0f);
            }
            for (int64_t c = 0; c < d; c++) {
                vf out = dot(hdn, w2 + c * m, m, splat(b2[c])) + init[c];
                store_lanes(ye + c * S + i0, out, nl);
            }
        }
    }
}

// Entries [e0, e1) of x [n][d][S] (entry stride x_stride) -> y (y_stride); w1 [m, d], b1 [m], w2 [d, m], b2 [d];
// code null or [n][S][d].  d <= graf_block_limits(0), m <= graf_block_limits(1).
extern "C" void graf_mlp(const float *w1, const float *b1, const float *w2, const float *b2, int64_t d, int64_t m,
                         const float *x, int64_t x_stride, const float *code, float *y, int64_t y_stride, int64_t e0,
                         int64_t e1, int64_t S) {
    if (d == 16 && m == 64)  // GRaF's MLP2
        mlp_entries<16, 64>(w1, b1, w2, b2, d, m, x, x_stride, code, y, y_stride, e0, e1, S);
    else
        mlp_entries<0, 0>(w1, b1, w2, b2, d, m, x, x_stride, code, y, y_stride, e0, e1, S);
}

// ------------------------------------------------------------------------------------------------ whole rays
// GRaF's rays from their voxel queries to their pooled state, one ray at a time with everything in cache: the
// scene blocks (cross-attention over the ray's own tokens), MLP2 plus the distance code, the ray transformer's
// blocks, the mean over the ray.  The same arithmetic as graf_block and graf_mlp in turn.
struct RayPass {
    const BlockWeights *const *scene;  // n_scene scene blocks (cross-attention)
    const BlockWeights *const *ray;    // n_ray ray blocks (self-attention)
    const float *w1, *b1, *w2, *b2;    // MLP2: [m, d], [m], [d, m], [d]
    int64_t n_scene, n_ray, d, m;
};

static void graf_block_one(const BlockWeights *w, const float *x, float *y, int64_t S, const float *ctx, int64_t L,
                           const uint8_t *mask) {
    graf_block(w, x, 0, y, 0, 0, 1, S, ctx, 0, L, mask, 0);
}

// Rays [e0, e1): queries x [n][S][d] and tokens [n or 1][L][d] token-major (tok_stride: 0 = shared), key mask
// [n or 1][L] (mask_stride) or null, distance code [n][S][d]; out [n][d].
extern "C" void graf_ray_pass(const RayPass *p, const float *x, const float *tok, int64_t tok_stride, int64_t L,
                              const uint8_t *mask, int64_t mask_stride, const float *code, float *out, int64_t e0,
                              int64_t e1, int64_t S) {
    const int64_t d = p->d;
    static thread_local std::vector<float> a, b, c;
    a.resize((size_t)(d * S));
    b.resize((size_t)(d * S));
    c.resize((size_t)(d * L));
    for (int64_t e = e0; e < e1; e++) {
        const float *xe = x + e * S * d, *te = tok + e * tok_stride;
        for (int64_t i = 0; i < S; i++)
            for (int64_t k = 0; k < d; k++) a[k * S + i] = xe[i * d + k];
        for (int64_t j = 0; j < L; j++)
            for (int64_t k = 0; k < d; k++) c[k * L + j] = te[j * d + k];
        const uint8_t *me = mask ? mask + e * mask_stride : nullptr;
        float *src = a.data(), *dst = b.data();
        for (int64_t s = 0; s < p->n_scene; s++) {
            graf_block_one(p->scene[s], src, dst, S, c.data(), L, me);
            std::swap(src, dst);
        }
        graf_mlp(p->w1, p->b1, p->w2, p->b2, d, p->m, src, 0, code + e * S * d, dst, 0, 0, 1, S);
        std::swap(src, dst);
        for (int64_t s = 0; s < p->n_ray; s++) {
            graf_block_one(p->ray[s], src, dst, S, nullptr, 0, nullptr);
            std::swap(src, dst);
        }
        for (int64_t k = 0; k < d; k++) {
            float sum = 0.0f;
            for (int64_t i = 0; i < S; i++) sum += src[k * S + i];
            out[e * d + k] = sum / (float)S;
        }
    }
}

// ------------------------------------------------------------------------------------------------ rays in lanes
// The same ray pass with 16 *rays* per vector: the rays of a group all have S voxels, lane r holds ray r0 + r at
// every position, and each lane attends to its own ray's keys.  No lane idles whatever S (the position-major
// layout above fills a vector with 16 positions of one ray: a 3-voxel ray leaves 13 of 16 lanes idle).

// sum_k a[k] * b[k * stride] + init over vectors, in four chains
static inline vf dotv(const vf *a, const vf *b, int64_t n, vf init, int64_t stride) {
    vf s0 = init, s1 = splat(0.0f), s2 = splat(0.0f), s3 = splat(0.0f);
    int64_t k = 0;
    for (; k + 4 <= n; k += 4) {
        s0 += a[k] * b[k * stride];
        s1 += a[k + 1] * b[(k + 1) * stride];
        s2 += a[k + 2] * b[(k + 2) * stride];
        s3 += a[k + 3] * b[(k + 3) * stride];
    }
    for (; k < n; k++) s0 += a[k] * b[k * stride];
    return (s0 + s1) + (s2 + s3);
}

// One block over a group's positions X [d][S] (in place); ctx [d][L] (cross-attention: each lane its ray's
// tokens) or null (self-attention over X), key mask [L] (lanes 0 / 1) or null; kv: scratch [2*H*Dh][keys].
template <int D, int DH, int FF>
static void block_rays(const BlockWeights *w, vf *X, int64_t S, const vf *ctx, int64_t L, const vf *mask, vf *kv) {
    const int64_t d = SIZE(D, w->d), H = w->H, Dh = SIZE(DH, w->Dh), F = SIZE(FF, w->F), HD = H * Dh;
    const vf *src = ctx ? ctx : X;
    const int64_t keys = ctx ? L : S, R = 2 * HD;
    for (int64_t j = 0; j < keys; j++) {
        vf cv[MAX_MODEL];
        for (int64_t c = 0; c < d; c++) cv[c] = src[c * keys + j];
        for (int64_t r = 0; r < R; r++) kv[r * keys + j] = dot(cv, w->wkv + r * d, d, splat(w->bkv[r]));
    }
    const vf ninf = splat(-INFINITY), zero = splat(0.0f);
    static thread_local vf s[MAX_KEYS];
    for (int64_t i = 0; i < S; i++) {
        vf xv[MAX_MODEL], q[MAX_INNER], o[MAX_INNER], y[MAX_MODEL], hdn[MAX_INNER];
        for (int64_t c = 0; c < d; c++) xv[c] = X[c * S + i];
        for (int64_t r = 0; r < HD; r++) q[r] = dot(xv, w->wq + r * d, d, splat(w->bq[r]));
        for (int64_t h = 0; h < H; h++) {
            const vf *kh = kv + (h * 2 * Dh) * keys, *vh = kh + Dh * keys;
            vf mx = ninf;
            for (int64_t j = 0; j < keys; j++) {
                vf acc = dotv(q + h * Dh, kh + j, Dh, zero, keys);
                if (mask) acc = mask[j] > 0.0f ? acc : ninf;
                s[j] = acc;
                mx = acc > mx ? acc : mx;
            }
            vf sum = zero;
            vf *oh = o + h * Dh;
            for (int64_t e = 0; e < Dh; e++) oh[e] = zero;
            for (int64_t j = 0; j < keys; j++) {
                vf p = vexp2(s[j] - mx);
                if (mask) p = mask[j] > 0.0f ? p : zero;
                sum += p;
                for (int64_t e = 0; e < Dh; e++) oh[e] += p * vh[e * keys + j];
            }
            for (int64_t e = 0; e < Dh; e++) oh[e] = oh[e] / sum;
        }
        for (int64_t c = 0; c < d; c++) y[c] = dot(o, w->wo + c * HD, HD, splat(w->bo[c]) + xv[c]);
        layer_norm(y, d, w->g1, w->be1, w->eps1);
        for (int64_t f = 0; f < F; f++) {
            vf acc = dot(y, w->w1 + f * d, d, splat(w->b1[f]));
            hdn[f] = acc > 0.0f ? acc : zero;
        }
        for (int64_t c = 0; c < d; c++) xv[c] = dot(hdn, w->w2 + c * F, F, splat(w->b2[c]) + y[c]);
        layer_norm(xv, d, w->g2, w->be2, w->eps2);
        for (int64_t c = 0; c < d; c++) X[c * S + i] = xv[c];
    }
}

static void block_rays_any(const BlockWeights *w, vf *X, int64_t S, const vf *ctx, int64_t L, const vf *mask, vf *kv) {
    if (w->d == 16 && w->Dh == 8 && w->F == 64)
        block_rays<16, 8, 64>(w, X, S, ctx, L, mask, kv);
    else if (w->d == 16 && w->Dh == 16 && w->F == 64)
        block_rays<16, 16, 64>(w, X, S, ctx, L, mask, kv);
    else
        block_rays<0, 0, 0>(w, X, S, ctx, L, mask, kv);
}

// graf_ray_pass's contract, 16 rays per vector (the rays [e0, e1) all have S voxels).  Lanes past e1 are zeros.
extern "C" void graf_ray_pass_lanes(const RayPass *p, const float *x, const float *tok, int64_t tok_stride, int64_t L,
                                    const uint8_t *mask, int64_t mask_stride, const float *code, float *out,
                                    int64_t e0, int64_t e1, int64_t S) {
    const int64_t d = p->d, m = p->m;
    int64_t R = 0;
    for (int64_t s = 0; s < p->n_scene; s++) R = R > 2 * p->scene[s]->H * p->scene[s]->Dh ? R : 2 * p->scene[s]->H * p->scene[s]->Dh;
    for (int64_t s = 0; s < p->n_ray; s++) R = R > 2 * p->ray[s]->H * p->ray[s]->Dh ? R : 2 * p->ray[s]->H * p->ray[s]->Dh;
    static thread_local std::vector<vf> X, C, M, KV;
    X.resize((size_t)(d * S));
    C.resize((size_t)(d * L));
    M.resize((size_t)L);
    KV.resize((size_t)(R * (S > L ? S : L)));
    for (int64_t r0 = e0; r0 < e1; r0 += LANES) {
        const int64_t nl = e1 - r0 < LANES ? e1 - r0 : LANES;
        float lane[LANES];
        for (int64_t i = 0; i < S; i++)
            for (int64_t c = 0; c < d; c++) {
                for (int64_t l = 0; l < LANES; l++) lane[l] = l < nl ? x[((r0 + l) * S + i) * d + c] : 0.0f;
                std::memcpy(&X[c * S + i], lane, sizeof(vf));
            }
        for (int64_t j = 0; j < L; j++) {
            for (int64_t c = 0; c < d; c++) {
                for (int64_t l = 0; l < LANES; l++) lane[l] = l < nl ? tok[(r0 + l) * tok_stride + j * d + c] : 0.0f;
                std::memcpy(&C[c * L + j], lane, sizeof(vf));
            }
            for (int64_t l = 0; l < LANES; l++) lane[l] = (l >= nl || !mask || mask[(r0 + l) * mask_stride + j]) ? 1.0f : 0.0f;
            std::memcpy(&M[j], lane, sizeof(vf));
        }
        for (int64_t s = 0; s < p->n_scene; s++) block_rays_any(p->scene[s], X.data(), S, C.data(), L, mask ? M.data() : nullptr, KV.data());
        for (int64_t i = 0; i < S; i++) {  // MLP2 plus the distance code
            vf xv[MAX_MODEL], hdn[MAX_INNER];
            for (int64_t c = 0; c < d; c++) xv[c] = X[c * S + i];
            for (int64_t f = 0; f < m; f++) {
                vf acc = dot(xv, p->w1 + f * d, d, splat(p->b1[f]));
                hdn[f] = acc > 0.0f ? acc : splat(0.0f);
            }
            for (int64_t c = 0; c < d; c++) {
                for (int64_t l = 0; l < LANES; l++) lane[l] = l < nl ? code[((r0 + l) * S + i) * d + c] : 0.0f;
                vf cv;
                std::memcpy(&cv, lane, sizeof cv);
                X[c * S + i] = dot(hdn, p->w2 + c * m, m, splat(p->b2[c])) + cv;
            }
        }
        for (int64_t s = 0; s < p->n_ray; s++) block_rays_any(p->ray[s], X.data(), S, nullptr, 0, nullptr, KV.data());
        for (int64_t c = 0; c < d; c++) {
            vf sum = splat(0.0f);
            for (int64_t i = 0; i < S; i++) sum += X[c * S + i];
            sum = sum / (float)S;
            std::memcpy(lane, &sum, sizeof lane);
            for (int64_t l = 0; l < nl; l++) out[(r0 + l) * d + c] = lane[l];
        }
    }
}

// ------------------------------------------------------------------------------------------ training: attention
// Multi-head attention with a backward, for GRaF's training on a CPU (graf.models.graf.kernels.train): token-major
// operands as the projections write them (no transposes), 16 queries per vector, nothing of size queries x keys
// in memory.  Group g, position s, head h, feature e of q lives at q[g * qg + s * qs + h * qh + e] (likewise k, v);
// o and do are contiguous [G, Sq, H, Dh]; lse [G, H, 2, Sq]: each softmax row's maximum score, then the inverse of
// its denominator (what the backward recomputes the probabilities from).
// mask [G, Sk] (mask_stride; nonzero = attend; at least one key per group) or null.  Scores are scale * q . k.
struct AttnArgs {
    const float *q, *k, *v;
    const uint8_t *mask;
    int64_t qg, qs, qh, kg, ks, kh, vg, vs, vh, mask_stride;
    int64_t H, Dh, Sq, Sk;
    int64_t dqs, dks;  // the backward's outputs: elements from one position to the next in dq, and in dk and dv
    float scale;
};

static inline vf gather_lanes(const float *p, int64_t stride, int64_t nl) {
    float tmp[LANES] = {0};
    for (int64_t l = 0; l < nl; l++) tmp[l] = p[l * stride];
    vf v;
    std::memcpy(&v, tmp, sizeof v);
    return v;
}

// the scale * q . k of 16 queries (qv [Dh]) with key row kj [Dh]
static inline vf score(const vf *qv, const float *kj, int64_t Dh, float scale) {
    vf acc = splat(0.0f);
    for (int64_t e = 0; e < Dh; e++) acc += qv[e] * kj[e];
    return acc * scale;
}

// groups [g0, g1): o [G, Sq, H, Dh], lse [G, H, 2, Sq].  DH: the head size known at compile time (0: a->Dh)
template <int DH>
static void attn_train_fwd(const AttnArgs *a, float *o, float *lse, int64_t g0, int64_t g1) {
    const int64_t H = a->H, Dh = SIZE(DH, a->Dh), Sq = a->Sq, Sk = a->Sk;
    std::vector<vf> s_buf((size_t)Sk + 1);
    vf *s = s_buf.data();
    for (int64_t g = g0; g < g1; g++) {
        const uint8_t *mg = a->mask ? a->mask + g * a->mask_stride : nullptr;
        for (int64_t h = 0; h < H; h++) {
            const float *qh = a->q + g * a->qg + h * a->qh;
            const float *kh = a->k + g * a->kg + h * a->kh;
            const float *vh = a->v + g * a->vg + h * a->vh;
            for (int64_t i0 = 0; i0 < Sq; i0 += LANES) {
                const int64_t nl = Sq - i0 < LANES ? Sq - i0 : LANES;
                vf qv[MAX_DIM], out[MAX_DIM];
                for (int64_t e = 0; e < Dh; e++) qv[e] = gather_lanes(qh + i0 * a->qs + e, a->qs, nl);
                vf mx = splat(-INFINITY);
                for (int64_t j = 0; j < Sk; j++) {
                    if (mg && !mg[j]) continue;
                    s[j] = score(qv, kh + j * a->ks, Dh, a->scale);
                    mx = s[j] > mx ? s[j] : mx;
                }
                for (int64_t e = 0; e < Dh; e++) out[e] = splat(0.0f);
                vf sum = splat(0.0f);
                for (int64_t j = 0; j < Sk; j++) {
                    if (mg && !mg[j]) continue;
                    vf p = vexp(s[j] - mx);
                    sum += p;
                    const float *vj = vh + j * a->vs;
                    for (int64_t e = 0; e < Dh; e++) out[e] += p * vj[e];
                }
                float ot[MAX_DIM][LANES];
                const vf inv = 1.0f / sum;
                for (int64_t e = 0; e < Dh; e++) {
                    vf r = out[e] * inv;
                    std::memcpy(ot[e], &r, sizeof r);
                }
                float *lg = lse + (g * H + h) * 2 * Sq;  // the rows' maxima, then their denominators' inverses
                store_lanes(lg + i0, mx, nl);
                store_lanes(lg + Sq + i0, inv, nl);
                for (int64_t l = 0; l < nl; l++) {
                    float *ol = o + ((g * Sq + i0 + l) * H + h) * Dh;
                    for (int64_t e = 0; e < Dh; e++) ol[e] = ot[e][l];
                }
            }
        }
    }
}

extern "C" void graf_attn_train_fwd(const AttnArgs *a, float *o, float *lse, int64_t g0, int64_t g1) {
    if (a->Dh == 8)
        attn_train_fwd<8>(a, o, lse, g0, g1);
    else if (a->Dh == 16)
        attn_train_fwd<16>(a, o, lse, g0, g1);
    else
        attn_train_fwd<0>(a, o, lse, g0, g1);
}

// groups [g0, g1): from o, lse and do (contiguous [G, Sq, H, Dh]) the gradients dq, dk and dv (position stride
// dqs for dq, dks for dk and dv, heads then features contiguous: they may interleave in one buffer as the
// projections' outputs do; masked keys get 0).  The probabilities are recomputed, twice: with 16 queries per
// vector for dq, then with 16 keys per vector for dk and dv (sums over queries), so no vector is ever summed across
// its lanes.
template <int DH>
static void attn_train_bwd(const AttnArgs *a, const float *o, const float *lse, const float *dout, float *dq,
                           float *dk, float *dv, int64_t g0, int64_t g1) {
    const int64_t H = a->H, Dh = SIZE(DH, a->Dh), Sq = a->Sq, Sk = a->Sk, HD = H * Dh;
    static thread_local std::vector<float> delta;
    delta.resize((size_t)Sq);
    for (int64_t g = g0; g < g1; g++) {
        const uint8_t *mg = a->mask ? a->mask + g * a->mask_stride : nullptr;
        for (int64_t h = 0; h < H; h++) {
            const float *qh = a->q + g * a->qg + h * a->qh;
            const float *kh = a->k + g * a->kg + h * a->kh;
            const float *vh = a->v + g * a->vg + h * a->vh;
            const float *lh = lse + (g * H + h) * 2 * Sq, *ih = lh + Sq;  // maxima, inverse denominators
            // dq: 16 queries per vector
            for (int64_t i0 = 0; i0 < Sq; i0 += LANES) {
                const int64_t nl = Sq - i0 < LANES ? Sq - i0 : LANES;
                const int64_t row = (g * Sq + i0) * HD + h * Dh;  // o, do of query i0, head h
                float *dqr = dq + (g * Sq + i0) * a->dqs + h * Dh;
                vf qv[MAX_DIM], dov[MAX_DIM], dqv[MAX_DIM];
                vf dl = splat(0.0f);
                for (int64_t e = 0; e < Dh; e++) {
                    qv[e] = gather_lanes(qh + i0 * a->qs + e, a->qs, nl);
                    dov[e] = gather_lanes(dout + row + e, HD, nl);  // zero in unused lanes
                    dl += dov[e] * gather_lanes(o + row + e, HD, nl);
                    dqv[e] = splat(0.0f);
                }
                store_lanes(delta.data() + i0, dl, nl);
                vf lv = load_lanes(lh + i0, nl), iv = load_lanes(ih + i0, nl);
                for (int64_t j = 0; j < Sk; j++) {
                    if (mg && !mg[j]) continue;
                    const float *kj = kh + j * a->ks, *vj = vh + j * a->vs;
                    vf p = vexp(score(qv, kj, Dh, a->scale) - lv) * iv;
                    vf dp = splat(0.0f);
                    for (int64_t e = 0; e < Dh; e++) dp += dov[e] * vj[e];
                    vf ds = p * (dp - dl);
                    for (int64_t e = 0; e < Dh; e++) dqv[e] += ds * kj[e];
                }
                float t[LANES];
                for (int64_t e = 0; e < Dh; e++) {
                    vf r = dqv[e] * a->scale;
                    std::memcpy(t, &r, sizeof t);
                    for (int64_t l = 0; l < nl; l++) dqr[l * a->dqs + e] = t[l];
                }
            }
            // dk, dv: 16 keys per vector
            for (int64_t j0 = 0; j0 < Sk; j0 += LANES) {
                const int64_t nl = Sk - j0 < LANES ? Sk - j0 : LANES;
                vf kv[MAX_DIM], vv[MAX_DIM], dkv[MAX_DIM], dvv[MAX_DIM];
                float live[LANES] = {0};
                for (int64_t l = 0; l < nl; l++) live[l] = (mg && !mg[j0 + l]) ? 0.0f : 1.0f;
                vf lane_on;
                std::memcpy(&lane_on, live, sizeof lane_on);
                for (int64_t e = 0; e < Dh; e++) {
                    kv[e] = gather_lanes(kh + j0 * a->ks + e, a->ks, nl);
                    vv[e] = gather_lanes(vh + j0 * a->vs + e, a->vs, nl);
                    dkv[e] = dvv[e] = splat(0.0f);
                }
                for (int64_t i = 0; i < Sq; i++) {
                    const float *qi = qh + i * a->qs, *doi = dout + (g * Sq + i) * HD + h * Dh;
                    vf s = splat(0.0f);
                    for (int64_t e = 0; e < Dh; e++) s += kv[e] * qi[e];
                    // masked and unused key lanes: the score is clamped far below the maximum, then zeroed
                    vf x = s * a->scale - lh[i];
                    x = x < 0.0f ? x : splat(0.0f);
                    vf p = vexp(x) * (lane_on * ih[i]);
                    vf dp = splat(0.0f);
                    for (int64_t e = 0; e < Dh; e++) dp += vv[e] * doi[e];
                    vf ds = p * (dp - delta[i]);
                    for (int64_t e = 0; e < Dh; e++) {
                        dvv[e] += p * doi[e];
                        dkv[e] += ds * qi[e];
                    }
                }
                float tk[MAX_DIM][LANES], tv[MAX_DIM][LANES];
                for (int64_t e = 0; e < Dh; e++) {
                    vf r = dkv[e] * a->scale;
                    std::memcpy(tk[e], &r, sizeof r);
                    std::memcpy(tv[e], &dvv[e], sizeof r);
                }
                for (int64_t l = 0; l < nl; l++) {
                    float *dkj = dk + (g * Sk + j0 + l) * a->dks + h * Dh, *dvj = dv + (g * Sk + j0 + l) * a->dks + h * Dh;
                    for (int64_t e = 0; e < Dh; e++) {
                        dkj[e] = tk[e][l];
                        dvj[e] = tv[e][l];
                    }
                }
            }
        }
    }
}

extern "C" void graf_attn_train_bwd(const AttnArgs *a, const float *o, const float *lse, const float *dout, float *dq,
                                    float *dk, float *dv, int64_t g0, int64_t g1) {
    if (a->Dh == 8)
        attn_train_bwd<8>(a, o, lse, dout, dq, dk, dv, g0, g1);
    else if (a->Dh == 16)
        attn_train_bwd<16>(a, o, lse, dout, dq, dk, dv, g0, g1);
    else
        attn_train_bwd<0>(a, o, lse, dout, dq, dk, dv, g0, g1);
}
