// sin of float32 CPU tensors through SLEEF, as an autograd function whose derivative, cos,
// goes through SLEEF as well, with cos's derivative −sin: gradients of every order (the
// regularisers' double backward included) stay exact. libtorch computes float32 sin and cos
// on the CPU with MKL's VML; SLEEF's AVX2 functions, which the wheel's libtorch exports (it
// uses them for its own bfloat16 and half sines), are faster (nn/sine.rs says by how much).
// nn/sine.rs is the only user.
#include <ATen/ATen.h>
#include <ATen/TensorIterator.h>
#include <torch/csrc/autograd/custom_function.h>

#include <cstring>

#include "../bridge_error.hpp"

#if defined(__x86_64__)
#include <immintrin.h>

extern "C" {
__m256 Sleef_sinf8_u35(__m256);
__m256 Sleef_cosf8_u35(__m256);
__m256 Sleef_sinf8_u10(__m256);
__m256 Sleef_cosf8_u10(__m256);
}
#endif

namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

#if defined(__x86_64__)
// Eight sines or cosines. SLEEF's 3.5-ULP functions hold their bound for |x| < 125 000 and
// cost about 1 ns an element on any argument; the 1.0-ULP ones take over 5 ns from |x| > 125
// on (measured on the AMD EPYC), and used throughout they saved little in training. A
// vector with a lane beyond 125 000 (or not finite) goes through the 1.0-ULP ones, which hold
// for every argument. Only the functions marked with the target attribute are compiled for
// AVX2 and FMA (not the file), so no inline function of libtorch's headers is emitted with
// those instructions; they run only where CPUID reports both.
__attribute__((target("avx2,fma"))) inline __m256 sine8(__m256 v, bool cosine) {
  const __m256 magnitude = _mm256_andnot_ps(_mm256_set1_ps(-0.0f), v);
  // Not-less-than, unordered: true for NaN as well.
  const bool wide = _mm256_movemask_ps(_mm256_cmp_ps(magnitude, _mm256_set1_ps(125000.0f), _CMP_NLT_UQ)) != 0;
  if (wide) return cosine ? Sleef_cosf8_u10(v) : Sleef_sinf8_u10(v);
  return cosine ? Sleef_cosf8_u35(v) : Sleef_sinf8_u35(v);
}

// y[i] = sin(x[i]) or cos(x[i]) for i < n.
__attribute__((target("avx2,fma"))) void sine_avx2(const float* x, float* y, int64_t n, bool cosine) {
  int64_t i = 0;
  for (; i + 8 <= n; i += 8) _mm256_storeu_ps(y + i, sine8(_mm256_loadu_ps(x + i), cosine));
  if (i < n) {
    // The tail through a zeroed buffer: nothing read or written past the range.
    float buf[8] = {0};
    std::memcpy(buf, x + i, static_cast<size_t>(n - i) * sizeof(float));
    _mm256_storeu_ps(buf, sine8(_mm256_loadu_ps(buf), cosine));
    std::memcpy(y + i, buf, static_cast<size_t>(n - i) * sizeof(float));
  }
}

bool vector_path() {
  static const bool ok = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return ok;
}
#else
bool vector_path() { return false; }
#endif

// sin(x) or cos(x) of a float32 CPU tensor, outside autograd; libtorch's own where the CPU
// lacks AVX2 and FMA. The loop runs through TensorIterator::for_each, which libtorch
// compiled with its OpenMP: this file is not (at::parallel_for, inline, would run serially
// here while libtorch's worker threads spin).
at::Tensor map(const at::Tensor& x, bool cosine) {
#if defined(__x86_64__)
  if (vector_path()) {
    at::Tensor out = at::empty_like(x, at::MemoryFormat::Contiguous);
    auto iter = at::TensorIteratorConfig().add_output(out).add_const_input(x).build();
    iter.for_each([cosine](char** data, const int64_t* strides, int64_t n) {
      auto* y = reinterpret_cast<float*>(data[0]);
      const auto* in = reinterpret_cast<const float*>(data[1]);
      if (strides[0] == sizeof(float) && strides[1] == sizeof(float)) {
        sine_avx2(in, y, n, cosine);
        return;
      }
      // A strided run (a view the iterator could not make contiguous): one at a time.
      for (int64_t i = 0; i < n; ++i) {
        sine_avx2(reinterpret_cast<const float*>(reinterpret_cast<const char*>(in) + i * strides[1]),
                  reinterpret_cast<float*>(reinterpret_cast<char*>(y) + i * strides[0]), 1, cosine);
      }
    });
    return out;
  }
#endif
  return cosine ? x.cos() : x.sin();
}

struct Cos;

struct Sin : public torch::autograd::Function<Sin> {
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& x) {
    ctx->save_for_backward({x});
    return map(x, false);
  }
  static variable_list backward(AutogradContext* ctx, variable_list grad);
};

struct Cos : public torch::autograd::Function<Cos> {
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& x) {
    ctx->save_for_backward({x});
    return map(x, true);
  }
  static variable_list backward(AutogradContext* ctx, variable_list grad) {
    auto x = ctx->get_saved_variables()[0];
    return {-grad[0] * Sin::apply(x)};
  }
};

variable_list Sin::backward(AutogradContext* ctx, variable_list grad) {
  auto x = ctx->get_saved_variables()[0];
  return {grad[0] * Cos::apply(x)};
}

}  // namespace

extern "C" {

// A new at::Tensor* holding sin(x) of `x` (an at::Tensor*, as tch holds it; float32 on the
// CPU), in autograd's graph where `x` requires grad. NULL on failure, with the reason in `err`.
void* gdrf_sin(void* x, char* err, size_t err_len) {
  at::Tensor* out = nullptr;
  gdrf::guarded(err, err_len, [&] {
    const at::Tensor& t = *static_cast<at::Tensor*>(x);
    TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat, "gdrf_sin takes float32 CPU tensors, got ",
                t.scalar_type(), " on ", t.device());
    out = new at::Tensor(Sin::apply(t));
  });
  return out;
}

// 1 where sines run through SLEEF's AVX2 code, 0 where libtorch's own are used.
int gdrf_sine_vectorised() { return vector_path() ? 1 : 0; }

}  // extern "C"
