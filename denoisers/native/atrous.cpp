// Fused kernels of the classical filters: the edge-aware a-trous iterations of SVGF and EAW and SVGF's
// temporal accumulation (denoisers/methods/svgf.py, eaw.py; the torch code there is the reference).
//
// The torch implementations run every tap pair as a handful of full-image ops, so they are bound by
// the memory traffic of the intermediate planes. Here one pass per iteration visits each centre
// pixel's 24 taps while the rows involved are in cache: rows are split across at::parallel_for
// workers (torch.set_num_threads applies), taps are the outer loop of a row and pixels the inner,
// contiguous and auto-vectorised loop. Symmetric per-pair terms are computed once for both taps of a
// pair (PairRows). Results do not depend on the thread count or on the vector width (no FMA
// contraction: -ffp-contract=off; a term shared between workers is recomputed bit-identically).
//
// Images are float32, channels-first (C, H, W), contiguous. Weights are exp2 of base-2 log-weights
// clamped at min_log2_weight, as in the torch code; exp2 and log are evaluated by the branch-free
// polynomial helpers below (vectorisable; about 1 ulp), not by libm (scalar calls would not vectorise).
// The a-trous passes flush subnormals to zero (FlushSubnormals).

#include <torch/extension.h>

#include <ATen/Parallel.h>

#if defined(__SSE__)
#include <xmmintrin.h>
#endif

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <vector>

namespace {

// 1D B3-spline taps (1, 4, 6, 4, 1) / 16; the 5x5 kernel is their outer product.
constexpr double kB3[5] = {1.0 / 16, 1.0 / 4, 3.0 / 8, 1.0 / 4, 1.0 / 16};
constexpr int kRadius = 2;
constexpr double kLn2 = 0.69314718055994530942;

// Functions whose loops are compiled for x86-64-v4 (AVX-512) and x86-64-v3 (AVX2, FMA) as well as for the
// baseline x86-64, picked at load time by the CPU; with -ffp-contract=off (FMA only where std::fma is
// written) all clones compute bit-identical results.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define MCDN_VECTOR_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define MCDN_VECTOR_CLONES
#endif

// Pixel loops read several planes and write row accumulators that never overlap them; GCC would
// otherwise version each loop with run-time alias checks and, past 10 of them, not vectorise it.
#if defined(__GNUC__) && !defined(__clang__)
#define MCDN_PIXEL_LOOP _Pragma("GCC ivdep")
#else
#define MCDN_PIXEL_LOOP
#endif

// Pixel-loop helpers and bodies must be inlined into each vector clone to be compiled for its ISA.
#if defined(__GNUC__)
#define MCDN_INLINE inline __attribute__((always_inline))
#define MCDN_INLINE_LAMBDA __attribute__((always_inline))
#else
#define MCDN_INLINE inline
#define MCDN_INLINE_LAMBDA
#endif

// 2^max(x, lo) for lo >= -126. NaN propagates (as clamp_min + exp2 in torch), results above
// 2^127 are +inf. Round-to-nearest split x = k + f, |f| <= 1/2, 2^f by its degree-7 Taylor polynomial
// (truncation error < 1e-8 relative), 2^k by building the float's exponent bits.
MCDN_INLINE float exp2_clamped(float x, float lo) {
    const float t = x < lo ? lo : x;
    const float bounded = t < 127.0f ? t : 127.0f;
    // Adding and subtracting 1.5 * 2^23 rounds to the nearest integer (|bounded| < 2^22).
    const float k = (bounded + 12582912.0f) - 12582912.0f;
    const float f = bounded - k;
    float p = 1.5252733804059841e-05f;              // ln2^7 / 7!
    p = p * f + 1.5403530393381606e-04f;            // ln2^6 / 6!
    p = p * f + 1.3333558146428443e-03f;            // ln2^5 / 5!
    p = p * f + 9.6181291076284772e-03f;            // ln2^4 / 4!
    p = p * f + 5.5504108664821580e-02f;            // ln2^3 / 3!
    p = p * f + 2.4022650695910071e-01f;            // ln2^2 / 2!
    p = p * f + 6.9314718055994531e-01f;            // ln2
    p = p * f + 1.0f;
    const float scale = std::bit_cast<float>((static_cast<int32_t>(k) + 127) << 23);
    float r = p * scale;
    r = t > 127.0f ? std::numeric_limits<float>::infinity() : r;
    return t != t ? t : r;
}

// Natural log of a positive, normal, finite float (NaN propagates). x = m 2^e with m in
// [sqrt(1/2), sqrt(2)); log m = 2 atanh(s), s = (m - 1) / (m + 1), |s| <= 0.172, by its series to s^9
// (truncation error < 3e-9 relative); m - 1 is exact, so values near 1 keep full relative accuracy.
MCDN_INLINE float log_positive(float x) {
    const int32_t bits = std::bit_cast<int32_t>(x);
    const int32_t e = (bits - 0x3f3504f3) >> 23;      // 0x3f3504f3 = sqrt(1/2)
    const float m = std::bit_cast<float>(bits - (e << 23));
    const float s = (m - 1.0f) / (m + 1.0f);
    const float s2 = s * s;
    float series = 1.0f / 9.0f;
    series = series * s2 + 1.0f / 7.0f;
    series = series * s2 + 1.0f / 5.0f;
    series = series * s2 + 1.0f / 3.0f;
    const float log_m = 2.0f * s + 2.0f * s * (series * s2);
    // ln 2 split so that e ln2_hi is exact.
    const float ef = static_cast<float>(e);
    const float r = ef * 0.693145751953125f + (log_m + ef * 1.428606765330187e-06f);
    return x != x ? x : r;
}

// Flushes subnormal results and operands to zero on this thread while alive (x86 MXCSR FTZ and DAZ),
// restoring the previous mode after. Tiny weights (2^-86 after the clamp) and their squares in the
// variance sums would otherwise produce subnormals, which take a microcode path several times slower
// (measured 2.5x on the whole SVGF kernel). The changes are below 1.2e-38 in absolute terms.
class FlushSubnormals {
public:
#if defined(__SSE__)
    FlushSubnormals() : saved_(_mm_getcsr()) { _mm_setcsr(saved_ | 0x8040u); }
    ~FlushSubnormals() { _mm_setcsr(saved_); }

private:
    unsigned int saved_;
#endif
};

// at::parallel_for over [begin, end) with subnormals flushed in every worker (for the a-trous passes).
template <typename F>
void parallel_rows(int64_t begin, int64_t end, int64_t grain, const F& body) {
    at::parallel_for(begin, end, grain, [&](int64_t chunk_begin, int64_t chunk_end) {
        FlushSubnormals flush;
        body(chunk_begin, chunk_end);
    });
}

void check_image(const at::Tensor& image, const char* name, int64_t channels, int64_t height, int64_t width) {
    TORCH_CHECK(image.dim() == 3 && image.size(0) == channels && image.size(1) == height && image.size(2) == width,
                name, " must be (", channels, ", ", height, ", ", width, "), got ", image.sizes());
    TORCH_CHECK(image.scalar_type() == at::kFloat && image.device().is_cpu() && image.is_contiguous(),
                name, " must be a contiguous float32 CPU tensor");
}

// Rows per parallel chunk: about 16k pixels, so small images are not split into tiny tasks.
int64_t row_grain(int64_t width) { return std::max<int64_t>(1, 16384 / std::max<int64_t>(width, 1)); }

// One tap of the 5x5 kernel at a given step: offset, log2 of its kernel weight, and (for SVGF's depth
// term) the offset as a reduced direction (dy, dx) / g with length g * step.
struct Tap {
    int64_t dy, dx;
    float log2_h;
    float direction_y, direction_x;
    int64_t length;
    int pair;                     // index of the pair {+o, -o} in 0..11
    bool forward;                 // +o: dy > 0, or dy = 0 and dx > 0
};

constexpr int kPairs = 12;

// How a tap gets a symmetric per-pair value: computes it, computes and stores it, or loads it.
enum class PairValue { kCompute, kStore, kLoad };

// The 24 taps, the 12 forward ones first (a backward tap reads what its forward partner stored).
std::vector<Tap> taps_at_step(int64_t step) {
    std::vector<Tap> taps;
    for (int i = -kRadius; i <= kRadius; ++i) {
        for (int j = -kRadius; j <= kRadius; ++j) {
            if (i == 0 && j == 0) continue;
            const int g = std::gcd(std::abs(i), std::abs(j));
            const float log2_h = static_cast<float>(std::log2(kB3[kRadius + i] * kB3[kRadius + j]));
            // In row-major order, tap k and tap 23 - k are opposite and k >= 12 are the forward ones.
            const int index = static_cast<int>(taps.size());
            taps.push_back({int64_t{i} * step, int64_t{j} * step, log2_h, static_cast<float>(i / g),
                            static_cast<float>(j / g), g * step, std::min(index, 23 - index), index >= kPairs});
        }
    }
    std::stable_partition(taps.begin(), taps.end(), [](const Tap& tap) { return tap.forward; });
    return taps;
}

// Symmetric per-pair values, d(p, p + o) = d(p + o, p), computed once for both taps of a pair: the
// forward tap +o of row y stores them indexed by the centre's x, and the backward tap -o of row y + dy
// reads them at x - dx. A pair keeps the last dy + 1 rows. Rows of other workers (before ``first_row``)
// are not stored here; their values are recomputed, bit-identically since d is symmetric in floats too.
class PairRows {
public:
    PairRows(const std::vector<Tap>& taps, int64_t width, int64_t first_row) : width_(width), first_row_(first_row) {
        int64_t offset = 0;
        for (const Tap& tap : taps) {
            if (!tap.forward) continue;
            rows_[tap.pair] = tap.dy + 1;
            offset_[tap.pair] = offset;
            offset += rows_[tap.pair] * width;
        }
        values_.resize(offset);
    }

    // Where the forward tap of row y stores its values (indexed by x).
    float* store(const Tap& tap, int64_t y) { return slot(tap.pair, y); }

    // The values for the backward tap of row y, indexed by the centre's x; nullptr if not stored here.
    const float* load(const Tap& tap, int64_t y) {
        const int64_t partner_row = y + tap.dy;
        return partner_row < first_row_ ? nullptr : slot(tap.pair, partner_row) + tap.dx;
    }

private:
    float* slot(int pair, int64_t y) { return values_.data() + offset_[pair] + (y % rows_[pair]) * width_; }

    int64_t width_, first_row_;
    int64_t rows_[kPairs] = {}, offset_[kPairs] = {};
    std::vector<float> values_;
};

// Calls body(x, active) for every x in [lo, hi), in blocks of kBlock pixels with a constant trip count,
// which vectorise without a scalar remainder loop (a remainder of up to 15 pixels per row and tap ran
// scalar exp2 and log, a quarter of the time at 256 pixels per row). The last block is moved back to
// end at hi; its pixels that the previous block covered already get active = false and must then
// contribute nothing. Rows shorter than a block run one pixel at a time.
constexpr int64_t kBlock = 16;

template <typename Body>
MCDN_INLINE void for_each_pixel(int64_t lo, int64_t hi, const Body& body) {
    int64_t x = lo;
    for (; x + kBlock <= hi; x += kBlock) {
        MCDN_PIXEL_LOOP
        for (int64_t k = 0; k < kBlock; ++k) body(x + k, true);
    }
    if (x == hi) return;
    if (hi - lo >= kBlock) {
        const int64_t start = hi - kBlock, covered = x;
        MCDN_PIXEL_LOOP
        for (int64_t k = 0; k < kBlock; ++k) body(start + k, start + k >= covered);
    } else {
        for (; x < hi; ++x) body(x, true);
    }
}

// [lo, hi): the pixels x of a row whose tap x + dx lies in the image.
inline void tap_columns(int64_t dx, int64_t width, int64_t& lo, int64_t& hi) {
    lo = std::max<int64_t>(0, -dx);
    hi = std::min<int64_t>(width, width - dx);
}

// =====================================================================================================
// SVGF
// =====================================================================================================

// Per-frame planes (H * W each) and constants of the SVGF edge-stopping weight.
struct SvgfGuides {
    const float* normal[3];
    const float* depth;
    const float* gradient[2];     // dz/dx, dz/dy
    const float* depth_floor;     // (z eps_rel + 1e-6) ln 2
    int64_t height, width;
    float normal_scale;           // sigma_n log2 e
    float cosine_floor;
    float sigma_depth_ln2;        // sigma_z ln 2
    float min_log2_weight;
};

// One pass: input colour (3 planes), variance, luminance and a_l log2 e of the input; outputs.
struct SvgfPass {
    const float* color[3];
    const float* variance;
    const float* luminance;
    const float* luminance_scale;
    float* out_color[3];
    float* out_variance;          // unused unless the pass filters the variance
};

// Luminance and the horizontal [1, 2, 1] / 4 blur of the variance for rows [begin, end)
// (filters.gaussian_blur_3x3 blurs along x first; a border pixel averages itself 2/3 and its neighbour 1/3).
MCDN_VECTOR_CLONES
void svgf_prepare_rows(const SvgfPass& pass, float* luminance, float* blurred_x, int64_t width, int64_t begin,
                       int64_t end) {
    const float third4 = static_cast<float>(4.0 / 3.0);
    for (int64_t y = begin; y < end; ++y) {
        const int64_t row = y * width;
        const float* r = pass.color[0] + row;
        const float* g = pass.color[1] + row;
        const float* b = pass.color[2] + row;
        float* lum = luminance + row;
        MCDN_PIXEL_LOOP
        for (int64_t x = 0; x < width; ++x) {
            lum[x] = (r[x] * 0.2126f + g[x] * 0.7152f) + b[x] * 0.0722f;
        }
        const float* v = pass.variance + row;
        float* out = blurred_x + row;
        if (width < 2) {
            out[0] = v[0];
            continue;
        }
        MCDN_PIXEL_LOOP
        for (int64_t x = 1; x + 1 < width; ++x) {
            out[x] = (v[x] * 0.5f + v[x - 1] * 0.25f) + v[x + 1] * 0.25f;
        }
        out[0] = (v[0] * 0.5f + v[1] * 0.25f) * third4;
        out[width - 1] = (v[width - 1] * 0.5f + v[width - 2] * 0.25f) * third4;
    }
}

// Vertical blur of ``blurred_x`` and a_l log2 e = 1 / (ln2 (sigma_l sqrt(max(blur, 0)) + eps)).
MCDN_VECTOR_CLONES
void svgf_luminance_scale_rows(const float* blurred_x, float* scale, int64_t height, int64_t width,
                               float sigma_ln2, float epsilon_ln2, int64_t begin, int64_t end) {
    const float third4 = static_cast<float>(4.0 / 3.0);
    for (int64_t y = begin; y < end; ++y) {
        const float* centre = blurred_x + y * width;
        const float* up = blurred_x + std::max<int64_t>(y - 1, 0) * width;
        const float* down = blurred_x + std::min<int64_t>(y + 1, height - 1) * width;
        float* out = scale + y * width;
        // Border rows average themselves (2/3) and their one neighbour (1/3); a single row is not blurred.
        const float* other = y == 0 ? down : up;
        const bool interior = y > 0 && y + 1 < height;
        if (height < 2) {
            std::copy(centre, centre + width, out);
        } else if (interior) {
            MCDN_PIXEL_LOOP
            for (int64_t x = 0; x < width; ++x) out[x] = (centre[x] * 0.5f + up[x] * 0.25f) + down[x] * 0.25f;
        } else {
            MCDN_PIXEL_LOOP
            for (int64_t x = 0; x < width; ++x) out[x] = (centre[x] * 0.5f + other[x] * 0.25f) * third4;
        }
        MCDN_PIXEL_LOOP
        for (int64_t x = 0; x < width; ++x) {
            const float blurred = out[x];
            const float deviation = std::sqrt(blurred < 0.0f ? 0.0f : blurred);
            out[x] = 1.0f / (deviation * sigma_ln2 + epsilon_ln2);
        }
    }
}

// The a-trous pass for rows [begin, end). kVariance: also filter the variance (sum h^2 w^2 var / (sum h w)^2).
template <bool kVariance>
MCDN_VECTOR_CLONES
void svgf_pass_rows(const SvgfGuides& guides, const SvgfPass& pass, const std::vector<Tap>& taps,
                    int64_t begin, int64_t end) {
    const int64_t width = guides.width, height = guides.height;
    const float centre_h = static_cast<float>(kB3[kRadius] * kB3[kRadius]);
    std::vector<float> buffer(5 * width);
    float* acc_r = buffer.data();
    float* acc_g = acc_r + width;
    float* acc_b = acc_g + width;
    float* acc_w = acc_b + width;
    float* acc_v = acc_w + width;
    // a_z(p, o) log2 e = 1 / (ln2 (sigma_z |grad z . o| + eps(p))) of this row per pair of taps {+o, -o}.
    std::vector<float> depth_scales(kPairs * width);
    PairRows normal_terms(taps, width, begin);
    for (int64_t y = begin; y < end; ++y) {
        const int64_t row = y * width;
        for (const Tap& tap : taps) {
            if (!tap.forward) continue;    // once per pair
            float* out = depth_scales.data() + tap.pair * width;
            const float* gx = guides.gradient[0] + row;
            const float* gy = guides.gradient[1] + row;
            const float* floor_z = guides.depth_floor + row;
            const float direction_x = tap.direction_x, direction_y = tap.direction_y;
            const float depth_slope = guides.sigma_depth_ln2 * static_cast<float>(tap.length);
            MCDN_PIXEL_LOOP
            for (int64_t x = 0; x < width; ++x) {
                // The depth floor holds eps(p) ln2.
                out[x] = 1.0f / (floor_z[x] + std::fabs(gx[x] * direction_x + gy[x] * direction_y) * depth_slope);
            }
        }
        MCDN_PIXEL_LOOP
        for (int64_t x = 0; x < width; ++x) {
            acc_r[x] = pass.color[0][row + x] * centre_h;
            acc_g[x] = pass.color[1][row + x] * centre_h;
            acc_b[x] = pass.color[2][row + x] * centre_h;
            acc_w[x] = centre_h;
            if constexpr (kVariance) acc_v[x] = pass.variance[row + x] * (centre_h * centre_h);
        }
        const float* pn0 = guides.normal[0] + row;
        const float* pn1 = guides.normal[1] + row;
        const float* pn2 = guides.normal[2] + row;
        const float* pz = guides.depth + row;
        const float* pl = pass.luminance + row;
        const float* scale_l = pass.luminance_scale + row;
        for (const Tap& tap : taps) {
            const int64_t qy = y + tap.dy;
            if (qy < 0 || qy >= height) continue;
            int64_t lo, hi;
            tap_columns(tap.dx, width, lo, hi);
            // Neighbour planes indexed by the centre's x.
            const int64_t shift = qy * width + tap.dx;
            const float* qn0 = guides.normal[0] + shift;
            const float* qn1 = guides.normal[1] + shift;
            const float* qn2 = guides.normal[2] + shift;
            const float* qz = guides.depth + shift;
            const float* ql = pass.luminance + shift;
            const float* qr = pass.color[0] + shift;
            const float* qg = pass.color[1] + shift;
            const float* qb = pass.color[2] + shift;
            const float* qv = pass.variance + shift;
            const float* scale_z = depth_scales.data() + tap.pair * width;
            const float log2_h = tap.log2_h;
            const float normal_scale = guides.normal_scale, cosine_floor = guides.cosine_floor;
            const float min_log2 = guides.min_log2_weight;
            // The normal term sigma_n log max(n_p . n_q, floor) is symmetric: a forward tap computes and
            // stores it, the backward tap of the same pair reads it (or recomputes it in a worker's first rows).
            float* store = tap.forward ? normal_terms.store(tap, y) : nullptr;
            const float* stored = tap.forward ? nullptr : normal_terms.load(tap, y);
            const auto accumulate = [&]<PairValue kSource>() MCDN_INLINE_LAMBDA {
                for_each_pixel(lo, hi, [&](int64_t x, bool active) MCDN_INLINE_LAMBDA {
                    float normal_term;
                    if constexpr (kSource == PairValue::kLoad) {
                        normal_term = stored[x];
                    } else {
                        float cosine = (pn0[x] * qn0[x] + pn1[x] * qn1[x]) + pn2[x] * qn2[x];
                        cosine = cosine < cosine_floor ? cosine_floor : cosine;
                        normal_term = log_positive(cosine) * normal_scale;
                        if constexpr (kSource == PairValue::kStore) store[x] = normal_term;
                    }
                    float log2_w = normal_term + log2_h;
                    log2_w -= scale_z[x] * std::fabs(pz[x] - qz[x]);
                    log2_w -= scale_l[x] * std::fabs(pl[x] - ql[x]);
                    const float weight = exp2_clamped(log2_w, min_log2);
                    const float w = active ? weight : 0.0f;
                    acc_r[x] += w * qr[x];
                    acc_g[x] += w * qg[x];
                    acc_b[x] += w * qb[x];
                    acc_w[x] += w;
                    if constexpr (kVariance) acc_v[x] += (w * w) * qv[x];
                });
            };
            if (store != nullptr) {
                accumulate.template operator()<PairValue::kStore>();
            } else if (stored != nullptr) {
                accumulate.template operator()<PairValue::kLoad>();
            } else {
                accumulate.template operator()<PairValue::kCompute>();
            }
        }
        float* out_r = pass.out_color[0] + row;
        float* out_g = pass.out_color[1] + row;
        float* out_b = pass.out_color[2] + row;
        MCDN_PIXEL_LOOP
        for (int64_t x = 0; x < width; ++x) {
            out_r[x] = acc_r[x] / acc_w[x];
            out_g[x] = acc_g[x] / acc_w[x];
            out_b[x] = acc_b[x] / acc_w[x];
        }
        if constexpr (kVariance) {
            float* out_v = pass.out_variance + row;
            MCDN_PIXEL_LOOP
            for (int64_t x = 0; x < width; ++x) out_v[x] = acc_v[x] / (acc_w[x] * acc_w[x]);
        }
    }
}

// SVGF's variance-guided a-trous iterations (SVGF._atrous). illumination (3, H, W), variance (1, H, W),
// normal (3, H, W) unit or zero, depth (1, H, W) metres >= 0, gradient (2, H, W) [dz/dx, dz/dy] metres
// per pixel. Returns [filtered (3, H, W), output of the first pass (3, H, W)].
std::vector<at::Tensor> svgf_atrous(const at::Tensor& illumination, const at::Tensor& variance,
                                    const at::Tensor& normal, const at::Tensor& depth, const at::Tensor& gradient,
                                    int64_t iterations, double sigma_luminance, double sigma_normal,
                                    double sigma_depth, double cosine_floor, double luminance_epsilon,
                                    double depth_epsilon_relative, double min_log2_weight) {
    TORCH_CHECK(illumination.dim() == 3, "illumination must be (3, H, W), got ", illumination.sizes());
    const int64_t height = illumination.size(1), width = illumination.size(2);
    check_image(illumination, "illumination", 3, height, width);
    check_image(variance, "variance", 1, height, width);
    check_image(normal, "normal", 3, height, width);
    check_image(depth, "depth", 1, height, width);
    check_image(gradient, "gradient", 2, height, width);
    TORCH_CHECK(iterations >= 1 && iterations <= 62, "iterations must be in [1, 62], got ", iterations);
    TORCH_CHECK(min_log2_weight >= -126.0, "min_log2_weight must be >= -126");
    const int64_t plane = height * width;
    const auto options = illumination.options();
    // Per frame: depth floor; per pass: luminance, x-blurred variance, a_l; ping-pong colour and variance.
    at::Tensor scratch = at::empty({4, height, width}, options);
    float* depth_floor = scratch.data_ptr<float>();
    float* luminance = depth_floor + plane;
    float* blurred_x = luminance + plane;
    float* luminance_scale = blurred_x + plane;
    at::Tensor history = at::empty({3, height, width}, options);
    at::Tensor filtered = iterations == 1 ? history : at::empty({3, height, width}, options);
    at::Tensor colors = at::empty({2, 3, height, width}, options);
    at::Tensor variances = at::empty({2, 1, height, width}, options);

    const float* z = depth.data_ptr<float>();
    const float relative = static_cast<float>(depth_epsilon_relative);
    const float ln2 = static_cast<float>(kLn2);
    parallel_rows(0, plane, 1 << 16, [&](int64_t begin, int64_t end) {
        for (int64_t i = begin; i < end; ++i) depth_floor[i] = (z[i] * relative + 1e-6f) * ln2;
    });
    SvgfGuides guides{};
    for (int c = 0; c < 3; ++c) guides.normal[c] = normal.data_ptr<float>() + c * plane;
    guides.depth = z;
    guides.gradient[0] = gradient.data_ptr<float>();
    guides.gradient[1] = gradient.data_ptr<float>() + plane;
    guides.depth_floor = depth_floor;
    guides.height = height;
    guides.width = width;
    guides.normal_scale = static_cast<float>(sigma_normal / kLn2);
    guides.cosine_floor = static_cast<float>(cosine_floor);
    guides.sigma_depth_ln2 = static_cast<float>(sigma_depth * kLn2);
    guides.min_log2_weight = static_cast<float>(min_log2_weight);
    const float sigma_ln2 = static_cast<float>(sigma_luminance * kLn2);
    const float epsilon_ln2 = static_cast<float>(luminance_epsilon * kLn2);
    const int64_t grain = row_grain(width);

    const float* color_in = illumination.data_ptr<float>();
    const float* variance_in = variance.data_ptr<float>();
    for (int64_t i = 0; i < iterations; ++i) {
        const bool last = i + 1 == iterations;
        float* color_out = i == 0 ? history.data_ptr<float>()
                         : last   ? filtered.data_ptr<float>()
                                  : colors.data_ptr<float>() + (i % 2) * 3 * plane;
        float* variance_out = variances.data_ptr<float>() + (i % 2) * plane;
        SvgfPass pass{};
        for (int c = 0; c < 3; ++c) {
            pass.color[c] = color_in + c * plane;
            pass.out_color[c] = color_out + c * plane;
        }
        pass.variance = variance_in;
        pass.luminance = luminance;
        pass.luminance_scale = luminance_scale;
        pass.out_variance = variance_out;
        const std::vector<Tap> taps = taps_at_step(int64_t{1} << i);
        parallel_rows(0, height, grain, [&](int64_t begin, int64_t end) {
            svgf_prepare_rows(pass, luminance, blurred_x, width, begin, end);
        });
        parallel_rows(0, height, grain, [&](int64_t begin, int64_t end) {
            svgf_luminance_scale_rows(blurred_x, luminance_scale, height, width, sigma_ln2, epsilon_ln2, begin, end);
        });
        parallel_rows(0, height, grain, [&](int64_t begin, int64_t end) {
            if (last) {
                svgf_pass_rows<false>(guides, pass, taps, begin, end);   // the last variance is not used
            } else {
                svgf_pass_rows<true>(guides, pass, taps, begin, end);
            }
        });
        color_in = color_out;
        variance_in = variance_out;
    }
    return {filtered, history};
}

// Temporal accumulation of SVGF (SVGF._accumulate with a usable history), one pixel at a time: the
// consistency-weighted bilinear reprojection of the previous state and the moving averages. It repeats
// the torch ops one for one, with std::fma where torch's CPU kernels fuse (addcmul, lerp): the history
// length is a weighted mean of lengths, compared exactly with min_temporal_history later, so it has to
// come out bit-identical for both paths to pick the same variance estimate.
struct SvgfHistory {
    const float* state;           // (10, H, W) previous [illumination, moments, length, depth, normal]
    const float* motion;          // (2, H, W) pixels, previous position = centre + motion
    const float* valid;           // (1, H, W)
    const float* depth;           // (1, H, W) this frame's G-buffer depth
    const float* normal;          // (3, H, W) this frame's G-buffer normal
    const float* illumination;    // (3, H, W)
    const float* moments;         // (2, H, W)
    float* integrated;            // (3, H, W) out
    float* integrated_moments;    // (2, H, W) out
    float* length;                // (1, H, W) out
    int64_t height, width;
    float motion_limit, depth_tolerance, normal_cos, alpha_color, alpha_moments, min_weight, max_history;
};

// NaN and +-Inf -> 0, finite values clamped to [-limit, limit] (filters.sanitize).
inline float sanitized(float x, float limit) {
    const float clamped = std::min(std::max(x, -limit), limit);
    return std::fabs(x) <= std::numeric_limits<float>::max() ? clamped : 0.0f;   // false for NaN and Inf
}

// torch.lerp's formula, fused as in torch (exact at weight 0 and 1).
inline float lerp(float start, float end, float weight) {
    const float difference = end - start;
    return std::fabs(weight) < 0.5f ? std::fma(weight, difference, start)
                                    : std::fma(-difference, 1.0f - weight, end);
}

// The x86-64-v3/v4 clones have FMA instructions (std::fma is exact either way, a libm call otherwise)
// and vectorise the four taps' loads as gathers.
MCDN_VECTOR_CLONES
void svgf_temporal_rows(const SvgfHistory& h, int64_t begin, int64_t end) {
    const int64_t width = h.width, height = h.height;
    const int32_t plane = static_cast<int32_t>(height * width), columns = static_cast<int32_t>(width);
    const float last_row = static_cast<float>(height - 1), last_column = static_cast<float>(width - 1);
    const float motion_limit = h.motion_limit, depth_tolerance = h.depth_tolerance, normal_cos = h.normal_cos;
    const float min_weight = h.min_weight, max_history = h.max_history;
    const float alpha_color = h.alpha_color, alpha_moments = h.alpha_moments;
    const float* state = h.state;
    for (int64_t y = begin; y < end; ++y) {
        const int64_t row = y * width;
        const float* motion_x = h.motion + row;
        const float* motion_y = h.motion + plane + row;
        const float* valid_mask = h.valid + row;
        const float* depth = h.depth + row;
        const float* normal_x = h.normal + row;
        const float* normal_y = h.normal + plane + row;
        const float* normal_z = h.normal + 2 * plane + row;
        const float* illumination[3] = {h.illumination + row, h.illumination + plane + row,
                                        h.illumination + 2 * plane + row};
        const float* moments[2] = {h.moments + row, h.moments + plane + row};
        float* integrated[3] = {h.integrated + row, h.integrated + plane + row, h.integrated + 2 * plane + row};
        float* integrated_moments[2] = {h.integrated_moments + row, h.integrated_moments + plane + row};
        float* length_out = h.length + row;
        const float row_f = static_cast<float>(y);
        MCDN_PIXEL_LOOP
        for (int64_t x = 0; x < width; ++x) {
            // Bilinear footprint of the backward lookup (filters.bilinear_footprint).
            const float px = sanitized(motion_x[x], motion_limit) + static_cast<float>(x);
            const float py = sanitized(motion_y[x], motion_limit) + row_f;
            const float x0 = std::floor(px), y0 = std::floor(py);
            const float fx = px - x0, fy = py - y0;
            const float valid = sanitized(valid_mask[x], 1e8f) > 0.5f ? 1.0f : 0.0f;
            const float tolerance = depth[x] * depth_tolerance;
            float previous[6] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
            float weight_sum = 0.0f;
            // One bilinear tap: only taps inside the image, on valid pixels, with a consistent depth and
            // normal count. Called four times (no loop), so that the pixel loop vectorises with gathers.
            const auto accumulate = [&](float ty, float tx, float bilinear) {
                const bool inside = ty >= 0.0f && ty <= last_row && tx >= 0.0f && tx <= last_column;
                const int32_t tap = static_cast<int32_t>(std::clamp(ty, 0.0f, last_row)) * columns +
                                    static_cast<int32_t>(std::clamp(tx, 0.0f, last_column));
                const float depth_difference = std::fabs(state[6 * plane + tap] - depth[x]);
                float cosine = state[7 * plane + tap] * normal_x[x];
                cosine = std::fma(state[8 * plane + tap], normal_y[x], cosine);
                cosine = std::fma(state[9 * plane + tap], normal_z[x], cosine);
                const float consistent = (depth_difference <= tolerance ? 1.0f : 0.0f) *
                                         (cosine >= normal_cos ? 1.0f : 0.0f);
                const float weight = consistent * (bilinear * (inside ? 1.0f : 0.0f) * valid);
                for (int c = 0; c < 6; ++c) previous[c] = std::fma(state[c * plane + tap], weight, previous[c]);
                weight_sum += weight;
            };
            accumulate(y0, x0, (1.0f - fy) * (1.0f - fx));
            accumulate(y0, x0 + 1.0f, (1.0f - fy) * fx);
            accumulate(y0 + 1.0f, x0, fy * (1.0f - fx));
            accumulate(y0 + 1.0f, x0 + 1.0f, fy * fx);
            const float success = weight_sum > min_weight ? 1.0f : 0.0f;
            const float normaliser = std::max(weight_sum, min_weight);
#pragma GCC unroll 6
            for (int c = 0; c < 6; ++c) previous[c] /= normaliser;
            // success ? min(previous + 1, max) : 1
            const float length = (std::min(previous[5] + 1.0f, max_history) - 1.0f) * success + 1.0f;
            const float weight_color = std::max(1.0f / length, alpha_color);
            const float weight_moments = std::max(1.0f / length, alpha_moments);
#pragma GCC unroll 3
            for (int c = 0; c < 3; ++c) integrated[c][x] = lerp(previous[c], illumination[c][x], weight_color);
#pragma GCC unroll 2
            for (int c = 0; c < 2; ++c) {
                integrated_moments[c][x] = lerp(previous[3 + c], moments[c][x], weight_moments);
            }
            length_out[x] = length;
        }
    }
}

// SVGF's temporal accumulation with a history. state (10, H, W) of the previous frame; motion (2, H, W)
// and valid (1, H, W) as rendered (sanitised here); depth (1, H, W) metres and normal (3, H, W) unit
// G-buffer of this frame; illumination (3, H, W), moments (2, H, W) of this frame. Returns
// [integrated illumination (3, H, W), integrated moments (2, H, W), history length (1, H, W)].
std::vector<at::Tensor> svgf_temporal(const at::Tensor& state, const at::Tensor& motion, const at::Tensor& valid,
                                      const at::Tensor& depth, const at::Tensor& normal,
                                      const at::Tensor& illumination, const at::Tensor& moments,
                                      double depth_tolerance, double normal_cos, double alpha_color,
                                      double alpha_moments, double min_weight, double max_history) {
    TORCH_CHECK(depth.dim() == 3, "depth must be (1, H, W), got ", depth.sizes());
    const int64_t height = depth.size(1), width = depth.size(2);
    check_image(state, "state", 10, height, width);
    check_image(motion, "motion", 2, height, width);
    check_image(valid, "valid", 1, height, width);
    check_image(depth, "depth", 1, height, width);
    check_image(normal, "normal", 3, height, width);
    check_image(illumination, "illumination", 3, height, width);
    check_image(moments, "moments", 2, height, width);
    TORCH_CHECK(10 * height * width < (int64_t{1} << 31), "images must have fewer than 2^31 / 10 pixels");
    const auto options = depth.options();
    at::Tensor integrated = at::empty({3, height, width}, options);
    at::Tensor integrated_moments = at::empty({2, height, width}, options);
    at::Tensor length = at::empty({1, height, width}, options);
    SvgfHistory h{state.data_ptr<float>(), motion.data_ptr<float>(), valid.data_ptr<float>(),
                  depth.data_ptr<float>(), normal.data_ptr<float>(), illumination.data_ptr<float>(),
                  moments.data_ptr<float>(), integrated.data_ptr<float>(), integrated_moments.data_ptr<float>(),
                  length.data_ptr<float>(), height, width,
                  // filters.sanitize (limit 1e8), then bilinear_footprint's 4 (H + W).
                  static_cast<float>(std::min(1e8, 4.0 * static_cast<double>(height + width))),
                  static_cast<float>(depth_tolerance), static_cast<float>(normal_cos),
                  static_cast<float>(alpha_color), static_cast<float>(alpha_moments), static_cast<float>(min_weight),
                  static_cast<float>(max_history)};
    at::parallel_for(0, height, row_grain(width), [&](int64_t begin, int64_t end) {
        svgf_temporal_rows(h, begin, end);
    });
    return {integrated, integrated_moments, length};
}

// =====================================================================================================
// EAW
// =====================================================================================================

// One EAW pass with G geometry channels for rows [begin, end): w = exp2(log2 h - |f_p - f_q|^2),
// f = [colour features, geometry], both already scaled so that the squared distance is base 2.
template <int G>
MCDN_VECTOR_CLONES
void eaw_pass_rows(const float* const* color, const float* const* features, const float* const* geometry,
                   float* const* out, const std::vector<Tap>& taps, int64_t height, int64_t width,
                   float min_log2, int64_t begin, int64_t end) {
    const float centre_h = static_cast<float>(kB3[kRadius] * kB3[kRadius]);
    std::vector<float> buffer(4 * width);
    float* acc_r = buffer.data();
    float* acc_g = acc_r + width;
    float* acc_b = acc_g + width;
    float* acc_w = acc_b + width;
    PairRows weights(taps, width, begin);
    for (int64_t y = begin; y < end; ++y) {
        const int64_t row = y * width;
        MCDN_PIXEL_LOOP
        for (int64_t x = 0; x < width; ++x) {
            acc_r[x] = color[0][row + x] * centre_h;
            acc_g[x] = color[1][row + x] * centre_h;
            acc_b[x] = color[2][row + x] * centre_h;
            acc_w[x] = centre_h;
        }
        const float* pf0 = features[0] + row;
        const float* pf1 = features[1] + row;
        const float* pf2 = features[2] + row;
        const float* pg[G > 0 ? G : 1];
        for (int k = 0; k < G; ++k) pg[k] = geometry[k] + row;
        for (const Tap& tap : taps) {
            const int64_t qy = y + tap.dy;
            if (qy < 0 || qy >= height) continue;
            int64_t lo, hi;
            tap_columns(tap.dx, width, lo, hi);
            const int64_t shift = qy * width + tap.dx;
            const float* qr = color[0] + shift;
            const float* qg = color[1] + shift;
            const float* qb = color[2] + shift;
            const float* qf0 = features[0] + shift;
            const float* qf1 = features[1] + shift;
            const float* qf2 = features[2] + shift;
            const float* qgeo[G > 0 ? G : 1];
            for (int k = 0; k < G; ++k) qgeo[k] = geometry[k] + shift;
            const float log2_h = tap.log2_h;
            // The weight is symmetric: a forward tap computes and stores it, the backward tap of the same
            // pair reads it (or recomputes it in a worker's first rows).
            float* store = tap.forward ? weights.store(tap, y) : nullptr;
            const float* stored = tap.forward ? nullptr : weights.load(tap, y);
            const auto accumulate = [&]<PairValue kSource>() MCDN_INLINE_LAMBDA {
                for_each_pixel(lo, hi, [&](int64_t x, bool active) MCDN_INLINE_LAMBDA {
                    float weight;
                    if constexpr (kSource == PairValue::kLoad) {
                        weight = stored[x];
                    } else {
                        float geometric = 0.0f;
                        for (int k = 0; k < G; ++k) {
                            const float d = pg[k][x] - qgeo[k][x];
                            geometric += d * d;
                        }
                        const float d0 = pf0[x] - qf0[x], d1 = pf1[x] - qf1[x], d2 = pf2[x] - qf2[x];
                        const float log2_w = ((log2_h - geometric) - d0 * d0 - d1 * d1) - d2 * d2;
                        weight = exp2_clamped(log2_w, min_log2);
                        if constexpr (kSource == PairValue::kStore) store[x] = weight;
                    }
                    const float w = active ? weight : 0.0f;
                    acc_r[x] += w * qr[x];
                    acc_g[x] += w * qg[x];
                    acc_b[x] += w * qb[x];
                    acc_w[x] += w;
                });
            };
            if (store != nullptr) {
                accumulate.template operator()<PairValue::kStore>();
            } else if (stored != nullptr) {
                accumulate.template operator()<PairValue::kLoad>();
            } else {
                accumulate.template operator()<PairValue::kCompute>();
            }
        }
        MCDN_PIXEL_LOOP
        for (int64_t x = 0; x < width; ++x) {
            out[0][row + x] = acc_r[x] / acc_w[x];
            out[1][row + x] = acc_g[x] / acc_w[x];
            out[2][row + x] = acc_b[x] / acc_w[x];
        }
    }
}

using EawPassRows = void (*)(const float* const*, const float* const*, const float* const*, float* const*,
                             const std::vector<Tap>&, int64_t, int64_t, float, int64_t, int64_t);

template <int... Gs>
EawPassRows eaw_pass_for(int64_t channels, std::integer_sequence<int, Gs...>) {
    EawPassRows table[] = {&eaw_pass_rows<Gs>...};
    return table[channels];
}

constexpr int kMaxEawGeometry = 8;

// EAW iterations (eaw.filter_eaw). color (3, H, W); geometry (G, H, W) with G <= 8, features already
// divided by their sigmas; feature_scales: per iteration, the factor turning colour into the colour
// feature (sqrt(log2 e) / sigma_i); geometry_scale: the same for the geometry (sqrt(log2 e)).
// Returns the filtered colour (3, H, W).
at::Tensor eaw_atrous(const at::Tensor& color, const at::Tensor& geometry, std::vector<double> feature_scales,
                      double geometry_scale, double min_log2_weight) {
    TORCH_CHECK(color.dim() == 3 && geometry.dim() == 3, "color and geometry must be (C, H, W)");
    const int64_t height = color.size(1), width = color.size(2), channels = geometry.size(0);
    check_image(color, "color", 3, height, width);
    check_image(geometry, "geometry", channels, height, width);
    TORCH_CHECK(channels <= kMaxEawGeometry, "at most ", kMaxEawGeometry, " geometry channels, got ", channels);
    TORCH_CHECK(!feature_scales.empty() && feature_scales.size() <= 62, "1 to 62 iterations (feature scales)");
    TORCH_CHECK(min_log2_weight >= -126.0, "min_log2_weight must be >= -126");
    const int64_t plane = height * width;
    const auto options = color.options();
    const int64_t iterations = static_cast<int64_t>(feature_scales.size());
    at::Tensor scaled_geometry = at::empty({std::max<int64_t>(channels, 1), height, width}, options);
    at::Tensor features = at::empty({3, height, width}, options);
    at::Tensor colors = at::empty({2, 3, height, width}, options);
    at::Tensor filtered = at::empty({3, height, width}, options);

    const float* geometry_in = geometry.data_ptr<float>();
    float* geometry_out = scaled_geometry.data_ptr<float>();
    const float g_scale = static_cast<float>(geometry_scale);
    parallel_rows(0, channels * plane, 1 << 16, [&](int64_t begin, int64_t end) {
        for (int64_t i = begin; i < end; ++i) geometry_out[i] = geometry_in[i] * g_scale;
    });
    const float* geometry_planes[kMaxEawGeometry > 0 ? kMaxEawGeometry : 1];
    for (int64_t k = 0; k < channels; ++k) geometry_planes[k] = geometry_out + k * plane;
    float* feature_planes[3];
    for (int c = 0; c < 3; ++c) feature_planes[c] = features.data_ptr<float>() + c * plane;
    const EawPassRows pass_rows = eaw_pass_for(channels, std::make_integer_sequence<int, kMaxEawGeometry + 1>{});
    const float min_log2 = static_cast<float>(min_log2_weight);
    const int64_t grain = row_grain(width);

    const float* color_in = color.data_ptr<float>();
    for (int64_t i = 0; i < iterations; ++i) {
        float* color_out = i + 1 == iterations ? filtered.data_ptr<float>()
                                               : colors.data_ptr<float>() + (i % 2) * 3 * plane;
        const float scale = static_cast<float>(feature_scales[i]);
        float* feature_out = features.data_ptr<float>();
        parallel_rows(0, 3 * plane, 1 << 16, [&](int64_t begin, int64_t end) {
            for (int64_t j = begin; j < end; ++j) feature_out[j] = color_in[j] * scale;
        });
        const float* color_planes[3];
        float* out_planes[3];
        for (int c = 0; c < 3; ++c) {
            color_planes[c] = color_in + c * plane;
            out_planes[c] = color_out + c * plane;
        }
        const std::vector<Tap> taps = taps_at_step(int64_t{1} << i);
        parallel_rows(0, height, grain, [&](int64_t begin, int64_t end) {
            pass_rows(color_planes, feature_planes, geometry_planes, out_planes, taps, height, width, min_log2,
                      begin, end);
        });
        color_in = color_out;
    }
    return filtered;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "Fused a-trous iterations of the SVGF and EAW denoisers (denoisers/native/atrous.cpp).";
    m.def("svgf_atrous", &svgf_atrous, "SVGF variance-guided a-trous iterations -> [filtered, first pass]");
    m.def("svgf_temporal", &svgf_temporal,
          "SVGF temporal accumulation -> [integrated illumination, integrated moments, history length]");
    m.def("eaw_atrous", &eaw_atrous, "EAW a-trous iterations -> filtered colour");
    m.attr("max_eaw_geometry") = kMaxEawGeometry;
}
