// Fused attention for many short sequences of narrow heads: GRaF's inference on a CPU (graf.models.graf.kernels).
// Compiled at first use by graf.models.graf.kernels.native (c++ -O3 -march=native), called through ctypes.
// 16 queries at a time in one vector: their scores against every key, the row maximum, exp and the
// value-weighted sums, all in registers; nothing of size queries x keys is written to memory.
#include <cmath>
#include <cstdint>
#include <cstring>

typedef float vf __attribute__((vector_size(64)));  // 16 lanes: 16 queries at once
typedef int32_t vi __attribute__((vector_size(64)));
static const int LANES = 16;
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
    vf s = (vf)e;
    return x < lo ? splat(0.0f) : p * s;
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
    static thread_local vf s[MAX_KEYS];
    for (int64_t b = b0; b < b1; b++) {
        const float *qb = q + b * q_stride, *kb = k + b * k_stride, *vb = v + b * v_stride;
        const uint8_t *mb = mask ? mask + b * mask_stride : nullptr;
        float *ob = o + b * o_stride;
        for (int64_t i0 = 0; i0 < Sq; i0 += LANES) {
            const int64_t nl = Sq - i0 < LANES ? Sq - i0 : LANES;
            vf qv[MAX_DIM];
            for (int64_t d = 0; d < Dk; d++) {
                float tmp[LANES] = {0};
                std::memcpy(tmp, qb + d * Sq + i0, nl * sizeof(float));
                std::memcpy(&qv[d], tmp, sizeof tmp);
            }
            vf mx = splat(-INFINITY);
            for (int64_t j = 0; j < Sk; j++) {
                if (mb && !mb[j]) continue;
                vf acc = qv[0] * kb[j];
                for (int64_t d = 1; d < Dk; d++) acc += qv[d] * kb[d * Sk + j];
                s[j] = acc;
                mx = acc > mx ? acc : mx;
            }
            vf out[MAX_DIM];
            for (int64_t d = 0; d < Dv; d++) out[d] = splat(0.0f);
            vf sum = splat(0.0f);
            for (int64_t j = 0; j < Sk; j++) {
                if (mb && !mb[j]) continue;
                vf e = vexp(s[j] - mx);
                sum += e;
                for (int64_t d = 0; d < Dv; d++) out[d] += e * vb[d * Sk + j];
            }
            for (int64_t d = 0; d < Dv; d++) {
                float tmp[LANES];
                vf r = out[d] / sum;
                std::memcpy(tmp, &r, sizeof tmp);
                std::memcpy(ob + d * Sq + i0, tmp, nl * sizeof(float));
            }
        }
    }
}
