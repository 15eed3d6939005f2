// Affinity kernel sums of Isik et al. 2021 (Sec. 3.4-3.5, Eq. 4-8) and their gradients: the forward and backward
// passes of denoisers/affinity.py (_sums_torch and _backward_torch are the references).
//
// For every pixel p and tap offset o_t = dilation * (i - k/2, j - k/2), i, j = 0..k-1 (row-major, top-left first):
//   w_t(p) = center(p)                                                   centre tap, when center is given,
//   w_t(p) = exp(-bandwidth(p) * D_t(p)),  D_t(p) = sum_d (features_d(p) - neighbours_d(p + o_t))^2,   otherwise,
//   num_c(p) = sum_t w_t(p) image_c(p + o_t),   den(p) = sum_t w_t(p).
// Taps with p + o_t outside the image get weight 0 and are left out of both sums (the reference's zero-padded
// windows times its inside mask). Rows (n, y) are split across at::parallel_for workers (torch.set_num_threads
// applies); within a row the taps are the outer loop, in the reference's row-major order, and the pixels the
// inner, contiguous loop (vectorised, the exp included: see fast_exp). Each output value is summed over the taps,
// and each distance over d, in ascending order whatever the thread count (deterministic); the results agree with
// the torch reference to float rounding (fast_exp, within 1 ulp of exp, against torch's vectorised exp).
//
// Backward (affinity_sums_backward), with gw_t(p) = sum_c grad_num_c(p) image_c(p + o_t) + grad_den(p) and, for
// the affinity taps, s_t(p) = -2 gw_t(p) w_t(p) bandwidth(p):
//   g_center(p) = gw_centre(p);   g_bandwidth(p) = -sum_t gw_t(p) w_t(p) D_t(p);
//   g_features(p) = sum_t s_t(p) (f(p) - g(p + o_t));   g_neighbours(q) = -sum_t s_t(q - o_t) (f(q - o_t) - g(q));
//   g_image(q) = sum_t w_t(q - o_t) grad_num(q - o_t)    (the centre tap included; affinity taps only otherwise).
// The scatter to q = p + o_t is done as a gather instead, so that every output value belongs to one worker (no
// atomics): pass 1 over pixels p gives g_features, g_bandwidth, g_center; pass 2 over pixels q recomputes w_t and
// s_t at p = q - o_t and gives g_image, g_neighbours. Both run over the taps in row-major order (that of the
// reference's accumulation), so the results are deterministic and independent of the thread count too.
//
// Tensors are float32, contiguous, CPU: image (N, C, H, W), features and neighbours (N, d, H, W), bandwidth and
// center (N, 1, H, W); size odd >= 1, dilation >= 1. Forward returns num (N, C, H, W) and den (N, 1, H, W);
// backward takes grad_num and grad_den of those shapes.

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

namespace {

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define MCDN_VECTOR_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define MCDN_VECTOR_CLONES
#endif

#if defined(__GNUC__) && !defined(__clang__)
#define MCDN_PIXEL_LOOP _Pragma("GCC ivdep")
#else
#define MCDN_PIXEL_LOOP
#endif

#if defined(__GNUC__)
#define MCDN_INLINE inline __attribute__((always_inline))
#else
#define MCDN_INLINE inline
#endif

struct Shapes {
    int64_t channels, dims, height, width, size, dilation;
};

// The helpers take row pointers already shifted so that index x addresses the values of output column x; d and c
// planes are `plane` apart. They are inlined into the (cloned) row functions.

// Zeroes one row of `width` floats in each of `count` planes.
MCDN_INLINE void zero_rows(float* row, int64_t count, int64_t plane, int64_t width) {
    for (int64_t k = 0; k < count; ++k) {
        std::fill(row + k * plane, row + k * plane + width, 0.0f);
    }
}

// exp(x) in float, branch-free and in plain C++ so that GCC vectorises the loops that call it (std::exp is a
// scalar libm call without -ffast-math) in both target clones; no FMA contraction (-ffp-contract=off), so the
// AVX2 and baseline clones, and any thread count, give bit-identical results.
//   x = n ln2 + r, n = nearest integer to x log2(e) (the 1.5 * 2^23 trick: adding it rounds to nearest even and
//   leaves n in the low mantissa bits), r = (x - n ln2_hi) - n ln2_lo (Cody-Waite: ln2_hi has 9 significant
//   bits, so n ln2_hi and the first subtraction are exact), |r| <= ln2 / 2;
//   e^r = 1 + r + r^2 P(r), P the degree-5 minimax polynomial of Cephes' expf, evaluated by Horner;
//   2^n built as the float with exponent field n + 127 (integer add and shift on the bits).
// Range: x < -87.3 gives exactly 0 (exp(-87.3) = 1.2e-38: every result of the kept range is a normal float,
// n >= -126); x > 88.376 gives +inf (the largest x with n <= 127; std::exp overflows only above 88.7228);
// NaN gives NaN; -0 and 0 give 1 exactly. The weights use x = -a D <= 0.
// Measured against exp in double over every float of [-87, 0] and of [0, 88] (standalone exhaustive check,
// baseline and -march=x86-64-v3 builds bit-identical): max relative error 8.31e-8 on [-87, 0] and 8.21e-8 on
// [0, 88], i.e. < 0.993 ulp (faithfully rounded); against std::exp(float) at most 1.19e-7 (1 ulp) apart.
MCDN_INLINE float fast_exp(float x) {
    constexpr float lower = -87.3f, upper = 88.376f;
    constexpr float log2e = 1.44269504088896341f;
    constexpr float ln2_hi = 0.693359375f, ln2_lo = -2.12194440e-4f;
    constexpr float magic = 12582912.0f;    // 1.5 * 2^23
    const float clamped = std::min(std::max(x, lower), upper);    // NaN passes through both
    const float shifted = clamped * log2e + magic;
    const float n = shifted - magic;
    const float r = (clamped - n * ln2_hi) - n * ln2_lo;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = (p * r) * r + r + 1.0f;
    uint32_t bits;
    std::memcpy(&bits, &shifted, sizeof bits);
    // The low mantissa bits of `shifted` hold n (two's complement, offset by the 2^22 bit of 1.5 * 2^23): adding
    // the bias and shifting into the exponent field drops the offset and the upper bits, leaving (n + 127) << 23.
    const uint32_t scale_bits = (bits + 127u) << 23;
    float scale;
    std::memcpy(&scale, &scale_bits, sizeof scale);
    const float y = p * scale;
    return x < lower ? 0.0f : (x > upper ? std::numeric_limits<float>::infinity() : y);
}

// distance[x] = sum_d (f_d[x] - g_d[x])^2 (ascending d) and weight[x] = exp(-a[x] distance[x]).
MCDN_INLINE void affinity_weights(const float* f, const float* g, const float* a, int64_t dims, int64_t plane,
                                  int64_t x_begin, int64_t x_end, float* distance, float* weight) {
    std::fill(distance + x_begin, distance + x_end, 0.0f);
    for (int64_t d = 0; d < dims; ++d) {
        const float* f_row = f + d * plane;
        const float* g_row = g + d * plane;
        MCDN_PIXEL_LOOP
        for (int64_t x = x_begin; x < x_end; ++x) {
            const float difference = f_row[x] - g_row[x];
            distance[x] += difference * difference;
        }
    }
    MCDN_PIXEL_LOOP
    for (int64_t x = x_begin; x < x_end; ++x) {
        weight[x] = fast_exp(-a[x] * distance[x]);
    }
}

// One affinity tap fused into one pass over the columns: distance, weight and both sums per pixel in registers,
// instead of the separate passes of affinity_weights and the sum loops (about half the memory traffic). DIMS and
// CHANNELS are compile-time so that the d and c loops unroll and GCC vectorises the column loop. The arithmetic
// and its order are those of the unfused path (distance summed over ascending d from 0, then exp, then one add
// to den and to each num_c), so both paths give bit-identical results.
template <int DIMS, int CHANNELS>
MCDN_INLINE void fused_tap(const float* __restrict f, const float* __restrict g, const float* __restrict a,
                           const float* __restrict in, float* __restrict out, float* __restrict den, int64_t plane,
                           int64_t x_begin, int64_t x_end) {
    MCDN_PIXEL_LOOP
    for (int64_t x = x_begin; x < x_end; ++x) {
        float distance = 0.0f;
        for (int d = 0; d < DIMS; ++d) {
            const float difference = f[d * plane + x] - g[d * plane + x];
            distance += difference * difference;
        }
        const float weight = fast_exp(-a[x] * distance);
        den[x] += weight;
        for (int c = 0; c < CHANNELS; ++c) {
            out[c * plane + x] += weight * in[c * plane + x];
        }
    }
}

// The fused tap for the (dims, channels) pairs the models use (3 colour channels; d = 1, 2, 4, 8 of Table 4);
// false when the pair has no instance (the caller takes the unfused path).
MCDN_INLINE bool fused_tap_for(int64_t dims, int64_t channels, const float* f, const float* g, const float* a,
                               const float* in, float* out, float* den, int64_t plane, int64_t x_begin,
                               int64_t x_end) {
    if (channels != 3) {
        return false;
    }
    switch (dims) {
        case 1: fused_tap<1, 3>(f, g, a, in, out, den, plane, x_begin, x_end); return true;
        case 2: fused_tap<2, 3>(f, g, a, in, out, den, plane, x_begin, x_end); return true;
        case 4: fused_tap<4, 3>(f, g, a, in, out, den, plane, x_begin, x_end); return true;
        case 8: fused_tap<8, 3>(f, g, a, in, out, den, plane, x_begin, x_end); return true;
        default: return false;
    }
}

// Rows [row_begin, row_end) of the flattened (N * H) output rows; scratch holds 2 * width floats.
MCDN_VECTOR_CLONES
void sum_rows(const float* image, const float* features, const float* neighbours, const float* bandwidth,
              const float* center, float* num, float* den, const Shapes& s, int64_t row_begin, int64_t row_end,
              float* scratch) {
    const int64_t width = s.width, height = s.height, plane = s.height * s.width;
    const int64_t radius = s.size / 2;
    float* distance = scratch;
    float* weight = scratch + width;
    for (int64_t row = row_begin; row < row_end; ++row) {
        const int64_t n = row / height, y = row % height;
        const float* feature_base = features + n * s.dims * plane + y * width;
        const float* neighbour_base = neighbours + n * s.dims * plane;
        const float* image_base = image + n * s.channels * plane;
        const float* bandwidth_row = bandwidth + n * plane + y * width;
        float* num_base = num + n * s.channels * plane + y * width;
        float* den_row = den + n * plane + y * width;
        zero_rows(num_base, s.channels, plane, width);
        zero_rows(den_row, 1, plane, width);
        for (int64_t i = 0; i < s.size; ++i) {
            const int64_t dy = (i - radius) * s.dilation;
            const int64_t sy = y + dy;
            if (sy < 0 || sy >= height) {
                continue;
            }
            for (int64_t j = 0; j < s.size; ++j) {
                const int64_t dx = (j - radius) * s.dilation;
                // Output columns whose tap column x + dx lies inside the image (may be empty).
                const int64_t x_begin = std::max<int64_t>(0, -dx);
                const int64_t x_end = std::min<int64_t>(width, width - dx);
                if (x_begin >= x_end) {
                    continue;
                }
                const bool is_center = center != nullptr && dy == 0 && dx == 0;
                if (!is_center && fused_tap_for(s.dims, s.channels, feature_base, neighbour_base + sy * width + dx,
                                                bandwidth_row, image_base + sy * width + dx, num_base, den_row,
                                                plane, x_begin, x_end)) {
                    continue;
                }
                const float* w_row;
                if (is_center) {
                    w_row = center + n * plane + y * width;
                } else {
                    affinity_weights(feature_base, neighbour_base + sy * width + dx, bandwidth_row, s.dims, plane,
                                     x_begin, x_end, distance, weight);
                    w_row = weight;
                }
                MCDN_PIXEL_LOOP
                for (int64_t x = x_begin; x < x_end; ++x) {
                    den_row[x] += w_row[x];
                }
                for (int64_t c = 0; c < s.channels; ++c) {
                    const float* in_row = image_base + c * plane + sy * width + dx;
                    float* out_row = num_base + c * plane;
                    MCDN_PIXEL_LOOP
                    for (int64_t x = x_begin; x < x_end; ++x) {
                        out_row[x] += w_row[x] * in_row[x];
                    }
                }
            }
        }
    }
}

// --- Backward ---------------------------------------------------------------------------------------------------

// g_weight[x] = sum_c grad_num_c[x] image_c[x] + grad_den[x]: d loss / d w_t.
MCDN_INLINE void weight_gradient(const float* grad_num, const float* image, const float* grad_den,
                                 int64_t channels, int64_t plane, int64_t x_begin, int64_t x_end, float* g_weight) {
    std::fill(g_weight + x_begin, g_weight + x_end, 0.0f);
    for (int64_t c = 0; c < channels; ++c) {
        const float* gn_row = grad_num + c * plane;
        const float* in_row = image + c * plane;
        MCDN_PIXEL_LOOP
        for (int64_t x = x_begin; x < x_end; ++x) {
            g_weight[x] += gn_row[x] * in_row[x];
        }
    }
    MCDN_PIXEL_LOOP
    for (int64_t x = x_begin; x < x_end; ++x) {
        g_weight[x] += grad_den[x];
    }
}

// scale[x] = -2 g_weight[x] weight[x] a[x] (d loss / d f(p) = scale (f(p) - g(p + o))), then
// out_d[x] += sign * scale[x] (f_d[x] - g_d[x]) for every d.
MCDN_INLINE void add_scaled_differences(const float* f, const float* g, const float* a, const float* g_weight,
                                        const float* weight, int64_t dims, int64_t plane, int64_t x_begin,
                                        int64_t x_end, float sign, float* scale, float* out) {
    MCDN_PIXEL_LOOP
    for (int64_t x = x_begin; x < x_end; ++x) {
        scale[x] = -2.0f * g_weight[x] * weight[x] * a[x];
    }
    for (int64_t d = 0; d < dims; ++d) {
        const float* f_row = f + d * plane;
        const float* g_row = g + d * plane;
        float* out_row = out + d * plane;
        MCDN_PIXEL_LOOP
        for (int64_t x = x_begin; x < x_end; ++x) {
            out_row[x] += sign * (scale[x] * (f_row[x] - g_row[x]));
        }
    }
}

// The backward passes' affinity taps fused into one pass over the columns, as fused_tap is for the forward:
// weight, d loss / d weight and every gradient update per pixel in registers instead of the separate row passes
// of weight_gradient, affinity_weights and add_scaled_differences. Same arithmetic in the same order, so both
// paths give bit-identical results. Pass 1 (at pixels p): g_bandwidth and g_features.
template <int DIMS, int CHANNELS>
MCDN_INLINE void fused_backward_pixels(const float* __restrict f, const float* __restrict g,
                                       const float* __restrict a, const float* __restrict in,
                                       const float* __restrict gn, const float* __restrict gd,
                                       float* __restrict gb, float* __restrict gf, int64_t plane, int64_t x_begin,
                                       int64_t x_end) {
    MCDN_PIXEL_LOOP
    for (int64_t x = x_begin; x < x_end; ++x) {
        float g_weight = 0.0f;
        for (int c = 0; c < CHANNELS; ++c) {
            g_weight += gn[c * plane + x] * in[c * plane + x];
        }
        g_weight += gd[x];
        float distance = 0.0f;
        for (int d = 0; d < DIMS; ++d) {
            const float difference = f[d * plane + x] - g[d * plane + x];
            distance += difference * difference;
        }
        const float weight = fast_exp(-a[x] * distance);
        gb[x] -= g_weight * weight * distance;
        const float scale = -2.0f * g_weight * weight * a[x];
        for (int d = 0; d < DIMS; ++d) {
            gf[d * plane + x] += 1.0f * (scale * (f[d * plane + x] - g[d * plane + x]));
        }
    }
}

// Pass 2 (at pixels q, the values of p = q - o_t indexed by q's column): g_image and g_neighbours.
template <int DIMS, int CHANNELS>
MCDN_INLINE void fused_backward_taps(const float* __restrict f, const float* __restrict g,
                                     const float* __restrict a, const float* __restrict image_q,
                                     const float* __restrict gn, const float* __restrict gd,
                                     float* __restrict gi, float* __restrict gg, int64_t plane, int64_t x_begin,
                                     int64_t x_end) {
    MCDN_PIXEL_LOOP
    for (int64_t x = x_begin; x < x_end; ++x) {
        float distance = 0.0f;
        for (int d = 0; d < DIMS; ++d) {
            const float difference = f[d * plane + x] - g[d * plane + x];
            distance += difference * difference;
        }
        const float weight = fast_exp(-a[x] * distance);
        float g_weight = 0.0f;
        for (int c = 0; c < CHANNELS; ++c) {
            gi[c * plane + x] += weight * gn[c * plane + x];
            g_weight += gn[c * plane + x] * image_q[c * plane + x];
        }
        g_weight += gd[x];
        const float scale = -2.0f * g_weight * weight * a[x];
        for (int d = 0; d < DIMS; ++d) {
            gg[d * plane + x] += -1.0f * (scale * (f[d * plane + x] - g[d * plane + x]));
        }
    }
}

// Which fused backward instance serves (dims, channels): the forward's pairs (3 colour channels; d = 1, 2, 4, 8).
enum class FusedBackward { none, d1, d2, d4, d8 };

MCDN_INLINE FusedBackward fused_backward_for(int64_t dims, int64_t channels) {
    if (channels != 3) {
        return FusedBackward::none;
    }
    switch (dims) {
        case 1: return FusedBackward::d1;
        case 2: return FusedBackward::d2;
        case 4: return FusedBackward::d4;
        case 8: return FusedBackward::d8;
        default: return FusedBackward::none;
    }
}

// One fused backward loop: pass 1 (AT_TAPS false: outputs g_bandwidth, g_features) or pass 2 (AT_TAPS true:
// g_image, g_neighbours); `image` is the image at the tap's pixel.
template <bool AT_TAPS, int DIMS>
MCDN_INLINE void fused_backward(const float* f, const float* g, const float* a, const float* image, const float* gn,
                                const float* gd, float* out_first, float* out_second, int64_t plane, int64_t x_begin,
                                int64_t x_end) {
    if constexpr (AT_TAPS) {
        fused_backward_taps<DIMS, 3>(f, g, a, image, gn, gd, out_first, out_second, plane, x_begin, x_end);
    } else {
        fused_backward_pixels<DIMS, 3>(f, g, a, image, gn, gd, out_first, out_second, plane, x_begin, x_end);
    }
}

// The instance of fused_backward that `dims` selects (not none). Plain calls, no lambda: every level must be
// inlined into the cloned row functions, or the loops are compiled for the baseline target only.
template <bool AT_TAPS>
MCDN_INLINE void run_fused_backward(FusedBackward dims, const float* f, const float* g, const float* a,
                                    const float* image, const float* gn, const float* gd, float* out_first,
                                    float* out_second, int64_t plane, int64_t x_begin, int64_t x_end) {
    switch (dims) {
        case FusedBackward::d1:
            fused_backward<AT_TAPS, 1>(f, g, a, image, gn, gd, out_first, out_second, plane, x_begin, x_end);
            break;
        case FusedBackward::d2:
            fused_backward<AT_TAPS, 2>(f, g, a, image, gn, gd, out_first, out_second, plane, x_begin, x_end);
            break;
        case FusedBackward::d4:
            fused_backward<AT_TAPS, 4>(f, g, a, image, gn, gd, out_first, out_second, plane, x_begin, x_end);
            break;
        default:
            fused_backward<AT_TAPS, 8>(f, g, a, image, gn, gd, out_first, out_second, plane, x_begin, x_end);
            break;
    }
}

struct BackwardInputs {
    const float *image, *features, *neighbours, *bandwidth, *center, *grad_num, *grad_den;
};

// Gradient outputs; nullptr where not wanted.
struct BackwardOutputs {
    float *image, *features, *neighbours, *bandwidth, *center;
};

// Pass 1, rows [row_begin, row_end) of pixels p: g_features, g_bandwidth, g_center at p. Scratch: 4 * width.
MCDN_VECTOR_CLONES
void backward_at_pixels(const BackwardInputs& in, const BackwardOutputs& out, const Shapes& s, int64_t row_begin,
                        int64_t row_end, float* scratch) {
    const int64_t width = s.width, height = s.height, plane = s.height * s.width;
    const int64_t radius = s.size / 2;
    float* distance = scratch;
    float* weight = scratch + width;
    float* g_weight = scratch + 2 * width;
    float* scale = scratch + 3 * width;
    const bool affinity_grads = out.features != nullptr || out.bandwidth != nullptr;
    const FusedBackward fused = fused_backward_for(s.dims, s.channels);
    for (int64_t row = row_begin; row < row_end; ++row) {
        const int64_t n = row / height, y = row % height;
        const int64_t pixel = n * plane + y * width;    // (n, 0, y, 0) of a one-channel tensor
        const float* f_row = in.features + n * s.dims * plane + y * width;
        const float* neighbour_base = in.neighbours + n * s.dims * plane;
        const float* image_base = in.image + n * s.channels * plane;
        const float* gn_row = in.grad_num + n * s.channels * plane + y * width;
        const float* a_row = in.bandwidth + pixel;
        float* gf_row = out.features != nullptr ? out.features + n * s.dims * plane + y * width : nullptr;
        float* gb_row = out.bandwidth != nullptr ? out.bandwidth + pixel : nullptr;
        if (gf_row != nullptr) {
            zero_rows(gf_row, s.dims, plane, width);
        }
        if (gb_row != nullptr) {
            zero_rows(gb_row, 1, plane, width);
        }
        for (int64_t i = 0; i < s.size; ++i) {
            const int64_t dy = (i - radius) * s.dilation;
            const int64_t sy = y + dy;
            if (sy < 0 || sy >= height) {
                continue;
            }
            for (int64_t j = 0; j < s.size; ++j) {
                const int64_t dx = (j - radius) * s.dilation;
                const int64_t x_begin = std::max<int64_t>(0, -dx);
                const int64_t x_end = std::min<int64_t>(width, width - dx);
                const bool centre = in.center != nullptr && dy == 0 && dx == 0;
                if (x_begin >= x_end || (centre ? out.center == nullptr : !affinity_grads)) {
                    continue;
                }
                if (centre) {    // the centre tap covers the whole row
                    weight_gradient(gn_row, image_base + sy * width + dx, in.grad_den + pixel, s.channels, plane,
                                    x_begin, x_end, g_weight);
                    std::copy(g_weight, g_weight + width, out.center + pixel);
                    continue;
                }
                const float* g_row = neighbour_base + sy * width + dx;
                if (gb_row != nullptr && gf_row != nullptr && fused != FusedBackward::none) {
                    const float* in_row = image_base + sy * width + dx;
                    const float* gd_row = in.grad_den + pixel;
                    run_fused_backward<false>(fused, f_row, g_row, a_row, in_row, gn_row, gd_row, gb_row, gf_row,
                                              plane, x_begin, x_end);
                    continue;
                }
                weight_gradient(gn_row, image_base + sy * width + dx, in.grad_den + pixel, s.channels, plane,
                                x_begin, x_end, g_weight);
                affinity_weights(f_row, g_row, a_row, s.dims, plane, x_begin, x_end, distance, weight);
                if (gb_row != nullptr) {
                    MCDN_PIXEL_LOOP
                    for (int64_t x = x_begin; x < x_end; ++x) {
                        gb_row[x] -= g_weight[x] * weight[x] * distance[x];
                    }
                }
                if (gf_row != nullptr) {
                    add_scaled_differences(f_row, g_row, a_row, g_weight, weight, s.dims, plane, x_begin, x_end,
                                           1.0f, scale, gf_row);
                }
            }
        }
    }
}

// Pass 2, rows [row_begin, row_end) of pixels q: g_image and g_neighbours at q, gathered from the pixels
// p = q - o_t whose tap t reads q. Scratch: 4 * width.
MCDN_VECTOR_CLONES
void backward_at_taps(const BackwardInputs& in, const BackwardOutputs& out, const Shapes& s, int64_t row_begin,
                      int64_t row_end, float* scratch) {
    const int64_t width = s.width, height = s.height, plane = s.height * s.width;
    const int64_t radius = s.size / 2;
    float* distance = scratch;
    float* weight = scratch + width;
    float* g_weight = scratch + 2 * width;
    float* scale = scratch + 3 * width;
    const FusedBackward fused = fused_backward_for(s.dims, s.channels);
    for (int64_t row = row_begin; row < row_end; ++row) {
        const int64_t n = row / height, y = row % height;
        const float* g_row = in.neighbours + n * s.dims * plane + y * width;
        const float* image_row = in.image + n * s.channels * plane + y * width;
        float* gi_row = out.image != nullptr ? out.image + n * s.channels * plane + y * width : nullptr;
        float* gg_row = out.neighbours != nullptr ? out.neighbours + n * s.dims * plane + y * width : nullptr;
        if (gi_row != nullptr) {
            zero_rows(gi_row, s.channels, plane, width);
        }
        if (gg_row != nullptr) {
            zero_rows(gg_row, s.dims, plane, width);
        }
        for (int64_t i = 0; i < s.size; ++i) {
            const int64_t dy = (i - radius) * s.dilation;
            const int64_t py = y - dy;                  // the row of p = q - o_t
            if (py < 0 || py >= height) {
                continue;
            }
            for (int64_t j = 0; j < s.size; ++j) {
                const int64_t dx = (j - radius) * s.dilation;
                // Columns x of q whose p column x - dx lies inside the image.
                const int64_t x_begin = std::max<int64_t>(0, dx);
                const int64_t x_end = std::min<int64_t>(width, width + dx);
                const bool centre = in.center != nullptr && dy == 0 && dx == 0;
                if (x_begin >= x_end || (centre && gi_row == nullptr)) {
                    continue;
                }
                // Values at p, indexed by the column x of q.
                const int64_t p_pixel = n * plane + py * width - dx;
                const float* f_row = in.features + n * s.dims * plane + py * width - dx;
                const float* gn_row = in.grad_num + n * s.channels * plane + py * width - dx;
                const float* a_row = in.bandwidth + p_pixel;
                if (!centre && gi_row != nullptr && gg_row != nullptr && fused != FusedBackward::none) {
                    const float* gd_row = in.grad_den + p_pixel;
                    run_fused_backward<true>(fused, f_row, g_row, a_row, image_row, gn_row, gd_row, gi_row, gg_row,
                                             plane, x_begin, x_end);
                    continue;
                }
                const float* w_row;
                if (centre) {
                    w_row = in.center + p_pixel;
                } else {
                    affinity_weights(f_row, g_row, a_row, s.dims, plane, x_begin, x_end, distance, weight);
                    w_row = weight;
                }
                if (gi_row != nullptr) {
                    for (int64_t c = 0; c < s.channels; ++c) {
                        const float* gn_c = gn_row + c * plane;
                        float* gi_c = gi_row + c * plane;
                        MCDN_PIXEL_LOOP
                        for (int64_t x = x_begin; x < x_end; ++x) {
                            gi_c[x] += w_row[x] * gn_c[x];
                        }
                    }
                }
                if (gg_row != nullptr && !centre) {
                    weight_gradient(gn_row, image_row, in.grad_den + p_pixel, s.channels, plane, x_begin, x_end,
                                    g_weight);
                    add_scaled_differences(f_row, g_row, a_row, g_weight, weight, s.dims, plane, x_begin, x_end,
                                           -1.0f, scale, gg_row);
                }
            }
        }
    }
}

void check_like(const at::Tensor& t, const char* name, const at::Tensor& image, int64_t channels) {
    TORCH_CHECK(t.dim() == 4 && t.size(0) == image.size(0) && t.size(2) == image.size(2) &&
                    t.size(3) == image.size(3) && (channels < 0 || t.size(1) == channels),
                "affinity_sums: ", name, " ", t.sizes(), " does not match image ", image.sizes(),
                channels < 0 ? std::string() : " with " + std::to_string(channels) + " channel(s)");
    TORCH_CHECK(t.scalar_type() == at::kFloat && t.device().is_cpu() && t.is_contiguous(),
                "affinity_sums: ", name, " must be a contiguous float32 CPU tensor, got ", t.scalar_type(),
                " on ", t.device());
}

void check_inputs(const at::Tensor& image, const at::Tensor& features, const at::Tensor& neighbours,
                  const at::Tensor& bandwidth, const std::optional<at::Tensor>& center, int64_t size,
                  int64_t dilation) {
    TORCH_CHECK(size >= 1 && size % 2 == 1, "affinity_sums: kernel size must be odd and >= 1, got ", size);
    TORCH_CHECK(dilation >= 1, "affinity_sums: dilation must be >= 1, got ", dilation);
    TORCH_CHECK(image.dim() == 4, "affinity_sums: image must be (N, C, H, W), got ", image.sizes());
    check_like(image, "image", image, -1);
    check_like(features, "features", image, -1);
    check_like(neighbours, "neighbours", image, features.size(1));
    check_like(bandwidth, "bandwidth", image, 1);
    if (center.has_value()) {
        check_like(*center, "center", image, 1);
    }
}

std::tuple<at::Tensor, at::Tensor> affinity_sums(const at::Tensor& image, const at::Tensor& features,
                                                 const at::Tensor& neighbours, const at::Tensor& bandwidth,
                                                 const std::optional<at::Tensor>& center, int64_t size,
                                                 int64_t dilation) {
    check_inputs(image, features, neighbours, bandwidth, center, size, dilation);
    const Shapes s{image.size(1), features.size(1), image.size(2), image.size(3), size, dilation};
    const int64_t batch = image.size(0);
    at::Tensor num = at::empty_like(image);
    at::Tensor den = at::empty({batch, 1, s.height, s.width}, image.options());
    if (num.numel() == 0 || den.numel() == 0) {
        return {num.zero_(), den.zero_()};
    }
    const float* image_data = image.data_ptr<float>();
    const float* feature_data = features.data_ptr<float>();
    const float* neighbour_data = neighbours.data_ptr<float>();
    const float* bandwidth_data = bandwidth.data_ptr<float>();
    const float* center_data = center.has_value() ? center->data_ptr<float>() : nullptr;
    float* num_data = num.data_ptr<float>();
    float* den_data = den.data_ptr<float>();
    const int64_t work = std::max<int64_t>(1, s.width * size * size * (s.dims + s.channels + 4));
    const int64_t grain = std::max<int64_t>(1, 262144 / work);
    at::parallel_for(0, batch * s.height, grain, [&](int64_t begin, int64_t end) {
        std::vector<float> scratch(2 * s.width);
        sum_rows(image_data, feature_data, neighbour_data, bandwidth_data, center_data, num_data, den_data, s,
                 begin, end, scratch.data());
    });
    return {num, den};
}

using MaybeTensor = std::optional<at::Tensor>;

std::tuple<MaybeTensor, MaybeTensor, MaybeTensor, MaybeTensor, MaybeTensor> affinity_sums_backward(
    const at::Tensor& image, const at::Tensor& features, const at::Tensor& neighbours, const at::Tensor& bandwidth,
    const std::optional<at::Tensor>& center, const at::Tensor& grad_num, const at::Tensor& grad_den, int64_t size,
    int64_t dilation, const std::vector<bool>& needs) {
    TORCH_CHECK(needs.size() == 5, "affinity_sums_backward: needs must hold 5 flags, got ", needs.size());
    check_inputs(image, features, neighbours, bandwidth, center, size, dilation);
    check_like(grad_num, "grad_num", image, image.size(1));
    check_like(grad_den, "grad_den", image, 1);
    const Shapes s{image.size(1), features.size(1), image.size(2), image.size(3), size, dilation};
    const int64_t rows = image.size(0) * s.height;
    auto output = [](bool wanted, const at::Tensor& like) {
        return wanted ? MaybeTensor(at::empty_like(like)) : MaybeTensor();
    };
    MaybeTensor g_image = output(needs[0], image), g_features = output(needs[1], features),
                g_neighbours = output(needs[2], neighbours), g_bandwidth = output(needs[3], bandwidth),
                g_center = output(needs[4] && center.has_value(), bandwidth);
    auto data = [](MaybeTensor& t) { return t.has_value() ? t->data_ptr<float>() : nullptr; };
    const BackwardInputs in{image.data_ptr<float>(), features.data_ptr<float>(), neighbours.data_ptr<float>(),
                            bandwidth.data_ptr<float>(), center.has_value() ? center->data_ptr<float>() : nullptr,
                            grad_num.data_ptr<float>(), grad_den.data_ptr<float>()};
    const BackwardOutputs out{data(g_image), data(g_features), data(g_neighbours), data(g_bandwidth),
                              data(g_center)};
    // Each pass writes every row of its outputs (empty tensors: no rows, nothing to do).
    const int64_t work = std::max<int64_t>(1, s.width * size * size * (2 * s.dims + 2 * s.channels + 6));
    const int64_t grain = std::max<int64_t>(1, 262144 / work);
    if (out.features != nullptr || out.bandwidth != nullptr || out.center != nullptr) {
        at::parallel_for(0, rows, grain, [&](int64_t begin, int64_t end) {
            std::vector<float> scratch(4 * s.width);
            backward_at_pixels(in, out, s, begin, end, scratch.data());
        });
    }
    if (out.image != nullptr || out.neighbours != nullptr) {
        at::parallel_for(0, rows, grain, [&](int64_t begin, int64_t end) {
            std::vector<float> scratch(4 * s.width);
            backward_at_taps(in, out, s, begin, end, scratch.data());
        });
    }
    return {g_image, g_features, g_neighbours, g_bandwidth, g_center};
}

}  // namespace

// How many distinct workers at::parallel_for gives `tasks` one-item tasks: what the build's OpenMP setting does
// with torch's thread count (1 when the extension was compiled without _OPENMP, whatever that count).
int64_t parallel_workers(int64_t tasks) {
    std::vector<int> used(static_cast<size_t>(std::max<int64_t>(1, at::get_num_threads())), 0);
    at::parallel_for(0, tasks, 1, [&](int64_t, int64_t) {
        const int id = at::get_thread_num();
        if (id >= 0 && static_cast<size_t>(id) < used.size()) {
            used[static_cast<size_t>(id)] = 1;
        }
    });
    return std::count(used.begin(), used.end(), 1);
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "Affinity kernel sums of Isik et al. 2021 (denoisers/native/affinity.cpp).";
    m.def("parallel_workers", &parallel_workers,
          "distinct at::parallel_for workers over `tasks` one-item tasks (1 without OpenMP)", pybind11::arg("tasks"));
    m.def("affinity_sums", &affinity_sums,
          "(num, den): w_t = exp(-a ||f(p) - g(p+o_t)||^2) (center(p) at the centre tap if given), 0 outside; "
          "num = sum_t w_t image(p+o_t), den = sum_t w_t",
          pybind11::arg("image"), pybind11::arg("features"), pybind11::arg("neighbours"), pybind11::arg("bandwidth"),
          pybind11::arg("center"), pybind11::arg("size"), pybind11::arg("dilation"));
    m.def("affinity_sums_backward", &affinity_sums_backward,
          "(g_image, g_features, g_neighbours, g_bandwidth, g_center) of affinity_sums given grad_num, grad_den; "
          "None where needs[i] is false (g_center also when center is None)",
          pybind11::arg("image"), pybind11::arg("features"), pybind11::arg("neighbours"), pybind11::arg("bandwidth"),
          pybind11::arg("center"), pybind11::arg("grad_num"), pybind11::arg("grad_den"), pybind11::arg("size"),
          pybind11::arg("dilation"), pybind11::arg("needs"));
}
