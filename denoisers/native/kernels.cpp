// Per-pixel kernel application, the inference hot loop of kernel-predicting denoisers (Bako et al. 2017,
// Vogels et al. 2018, Hasselgren et al. 2020; denoisers/kernels.py holds the torch reference and the API).
//
// out[c, y, x] = sum_{i, j} weights[i * k + j, y, x] * image[c, y + i - r, x + j - r],  r = k / 2,
// taps outside the image contribute nothing (zero padding, as torch's unfold in the reference); weights
// are used as given (the caller normalises or softmaxes them). Rows are split across at::parallel_for
// workers (torch.set_num_threads applies); within a row the taps are the outer loops and the pixels the
// inner, contiguous, vectorisable loop. Each output value is summed over the taps in ascending tap
// order whatever the thread count (deterministic); it agrees with the torch reference to float rounding.
// Inference only: no backward (training uses the torch reference, which autograd differentiates).
//
// Tensors are float32, contiguous, CPU: image (C, H, W), weights (k*k, H, W), k odd.

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>

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

// Rows [row_begin, row_end) of the output.
MCDN_VECTOR_CLONES
void apply_rows(const float* image, const float* weights, float* out, int64_t channels, int64_t height,
                int64_t width, int64_t size, int64_t row_begin, int64_t row_end) {
    const int64_t radius = size / 2;
    const int64_t plane = height * width;
    for (int64_t y = row_begin; y < row_end; ++y) {
        for (int64_t c = 0; c < channels; ++c) {
            float* out_row = out + c * plane + y * width;
            std::fill(out_row, out_row + width, 0.0f);
        }
        for (int64_t i = 0; i < size; ++i) {
            const int64_t sy = y + i - radius;
            if (sy < 0 || sy >= height) {
                continue;
            }
            for (int64_t j = 0; j < size; ++j) {
                const int64_t dx = j - radius;
                // Output columns whose tap column x + dx lies inside the image.
                const int64_t x_begin = std::max<int64_t>(0, -dx);
                const int64_t x_end = std::min<int64_t>(width, width - dx);
                const float* w_row = weights + (i * size + j) * plane + y * width;
                for (int64_t c = 0; c < channels; ++c) {
                    const float* in_row = image + c * plane + sy * width + dx;
                    float* out_row = out + c * plane + y * width;
                    MCDN_PIXEL_LOOP
                    for (int64_t x = x_begin; x < x_end; ++x) {
                        out_row[x] += w_row[x] * in_row[x];
                    }
                }
            }
        }
    }
}

at::Tensor apply_kernels(const at::Tensor& image, const at::Tensor& weights, int64_t size) {
    TORCH_CHECK(size >= 1 && size % 2 == 1, "kernel size must be odd and >= 1, got ", size);
    TORCH_CHECK(image.dim() == 3, "image must be (C, H, W), got ", image.sizes());
    const int64_t channels = image.size(0), height = image.size(1), width = image.size(2);
    TORCH_CHECK(weights.dim() == 3 && weights.size(0) == size * size && weights.size(1) == height &&
                    weights.size(2) == width,
                "weights must be (", size * size, ", ", height, ", ", width, "), got ", weights.sizes());
    for (const at::Tensor* t : {&image, &weights}) {
        TORCH_CHECK(t->scalar_type() == at::kFloat && t->device().is_cpu() && t->is_contiguous(),
                    "image and weights must be contiguous float32 CPU tensors");
    }
    at::Tensor out = at::empty({channels, height, width}, image.options());
    const float* image_data = image.data_ptr<float>();
    const float* weight_data = weights.data_ptr<float>();
    float* out_data = out.data_ptr<float>();
    const int64_t grain = std::max<int64_t>(1, 16384 / std::max<int64_t>(width, 1));
    at::parallel_for(0, height, grain, [&](int64_t begin, int64_t end) {
        apply_rows(image_data, weight_data, out_data, channels, height, width, size, begin, end);
    });
    return out;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "Per-pixel kernel application of kernel-predicting denoisers (denoisers/native/kernels.cpp).";
    m.def("apply_kernels", &apply_kernels, "out[c,y,x] = sum_t weights[t,y,x] image[c,y+dy_t,x+dx_t], zero padding",
          pybind11::arg("image"), pybind11::arg("weights"), pybind11::arg("size"));
}
