// Affinity kernel sums of Isik et al. 2021 (Sec. 3.4-3.5, Eq. 4-8), the forward pass of
// denoisers/affinity.py (_sums_torch is the reference; _AffinitySums keeps the torch backward).
//
// For every pixel p and tap offset o_t = dilation * (i - k/2, j - k/2), i, j = 0..k-1 (row-major, top-left first):
//   w_t(p) = center(p)                                                   centre tap, when center is given,
//   w_t(p) = exp(-bandwidth(p) * sum_d (features_d(p) - neighbours_d(p + o_t))^2)   otherwise,
//   num_c(p) = sum_t w_t(p) image_c(p + o_t),   den(p) = sum_t w_t(p).
// Taps with p + o_t outside the image get weight 0 and are left out of both sums (the reference's zero-padded
// windows times its inside mask). Rows (n, y) are split across at::parallel_for workers (torch.set_num_threads
// applies); within a row the taps are the outer loop, in the reference's row-major order, and the pixels the
// inner, contiguous loop (vectorised except the exp). Each output value is summed over the taps, and each
// distance over d, in ascending order whatever the thread count (deterministic); the results agree with the
// torch reference to float rounding (std::exp against torch's vectorised exp). Forward only: no backward.
//
// Tensors are float32, contiguous, CPU: image (N, C, H, W), features and neighbours (N, d, H, W), bandwidth and
// center (N, 1, H, W); size odd >= 1, dilation >= 1. Returns num (N, C, H, W) and den (N, 1, H, W).

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

namespace {

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define MCDN_VECTOR_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define MCDN_VECTOR_CLONES
#endif

#if defined(__GNUC__) && !defined(__clang__)
#define MCDN_PIXEL_LOOP _Pragma("GCC ivdep")
#else
#define MCDN_PIXEL_LOOP
#endif

struct Shapes {
    int64_t channels, dims, height, width, size, dilation;
};

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
        for (int64_t c = 0; c < s.channels; ++c) {
            std::fill(num_base + c * plane, num_base + c * plane + width, 0.0f);
        }
        std::fill(den_row, den_row + width, 0.0f);
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
                const float* w_row;
                if (center != nullptr && dy == 0 && dx == 0) {
                    w_row = center + n * plane + y * width;
                } else {
                    std::fill(distance + x_begin, distance + x_end, 0.0f);
                    for (int64_t d = 0; d < s.dims; ++d) {
                        const float* f_row = feature_base + d * plane;
                        const float* g_row = neighbour_base + d * plane + sy * width + dx;
                        MCDN_PIXEL_LOOP
                        for (int64_t x = x_begin; x < x_end; ++x) {
                            const float difference = f_row[x] - g_row[x];
                            distance[x] += difference * difference;
                        }
                    }
                    for (int64_t x = x_begin; x < x_end; ++x) {
                        weight[x] = std::exp(-bandwidth_row[x] * distance[x]);
                    }
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

void check_like(const at::Tensor& t, const char* name, const at::Tensor& image, int64_t channels) {
    TORCH_CHECK(t.dim() == 4 && t.size(0) == image.size(0) && t.size(2) == image.size(2) &&
                    t.size(3) == image.size(3) && (channels < 0 || t.size(1) == channels),
                "affinity_sums: ", name, " ", t.sizes(), " does not match image ", image.sizes(),
                channels < 0 ? std::string() : " with " + std::to_string(channels) + " channel(s)");
    TORCH_CHECK(t.scalar_type() == at::kFloat && t.device().is_cpu() && t.is_contiguous(),
                "affinity_sums: ", name, " must be a contiguous float32 CPU tensor, got ", t.scalar_type(),
                " on ", t.device());
}

std::tuple<at::Tensor, at::Tensor> affinity_sums(const at::Tensor& image, const at::Tensor& features,
                                                 const at::Tensor& neighbours, const at::Tensor& bandwidth,
                                                 const std::optional<at::Tensor>& center, int64_t size,
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

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "Affinity kernel sums of Isik et al. 2021 (denoisers/native/affinity.cpp).";
    m.def("affinity_sums", &affinity_sums,
          "(num, den): w_t = exp(-a ||f(p) - g(p+o_t)||^2) (center(p) at the centre tap if given), 0 outside; "
          "num = sum_t w_t image(p+o_t), den = sum_t w_t",
          pybind11::arg("image"), pybind11::arg("features"), pybind11::arg("neighbours"), pybind11::arg("bandwidth"),
          pybind11::arg("center"), pybind11::arg("size"), pybind11::arg("dilation"));
}
