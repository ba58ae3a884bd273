// nerfstudio's multi-resolution hash encoding, forward and backward with respect to the positions, for
// frozen tables on the CPU. One pass per point and level does what the torch version spreads over a
// dozen tensor operations (scale, floor, hash eight corners, gather, blend), so nothing is written to
// memory between them. When the positions need a gradient the same pass also writes the features'
// Jacobian, and the backward is a small contraction with it instead of a second round of gathers. Same
// hash, same table layout, same trilinear weights as
// nerfstudio.field_components.encodings.HashEncoding.pytorch_fwd.
#include <torch/extension.h>

#include <ATen/Parallel.h>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;

struct Level {
  float frac[3];  // per axis: the position's offset from the floor corner, in cells (the ceil corner's weight)
  uint32_t hash[3][2];
};

inline Level locate(const float* p, float scaling) {
  Level c;
  for (int a = 0; a < 3; ++a) {
    const float x = p[a] * scaling;
    const float lower = std::floor(x);
    const float frac = x - lower;
    c.frac[a] = frac;
    // nerfstudio takes the ceil, not floor + 1: on an exact grid point both corners are the same cell.
    const uint32_t ends[2] = {static_cast<uint32_t>(static_cast<int32_t>(lower)),
                              static_cast<uint32_t>(static_cast<int32_t>(std::ceil(x)))};
    const uint32_t prime = a == 0 ? 1u : (a == 1 ? kPrimeY : kPrimeZ);
    c.hash[a][0] = ends[0] * prime;
    c.hash[a][1] = ends[1] * prime;
  }
  return c;
}

// The inputs both passes read, checked once: positions [N, 3], table [T, F], one scaling and table
// offset per level.
struct Grid {
  int64_t n, levels, f;
  const float* pos;
  const float* tab;
  const float* scl;
  const int64_t* off;
  uint32_t mask;

  Grid(const torch::Tensor& positions, const torch::Tensor& table, const torch::Tensor& scalings,
       const torch::Tensor& offsets, int64_t table_size) {
    TORCH_CHECK(positions.device().is_cpu() && positions.scalar_type() == torch::kFloat32 && positions.dim() == 2 &&
                    positions.size(1) == 3 && positions.is_contiguous(),
                "positions must be a contiguous float32 CPU tensor [N, 3]");
    TORCH_CHECK(table.scalar_type() == torch::kFloat32 && table.dim() == 2 && table.is_contiguous(),
                "table must be a contiguous float32 tensor [T, F]");
    TORCH_CHECK(scalings.scalar_type() == torch::kFloat32 && scalings.is_contiguous(), "scalings must be float32");
    TORCH_CHECK(offsets.scalar_type() == torch::kInt64 && offsets.numel() == scalings.numel(),
                "offsets must be int64, one per level");
    n = positions.size(0);
    levels = scalings.numel();
    f = table.size(1);
    pos = positions.data_ptr<float>();
    tab = table.data_ptr<float>();
    scl = scalings.data_ptr<float>();
    off = offsets.data_ptr<int64_t>();
    mask = static_cast<uint32_t>(table_size - 1);
  }

  // The features of corner (x, y, z) of the cell ``c`` located on level ``l``.
  const float* row(const Level& c, int64_t l, int x, int y, int z) const {
    const uint32_t h = (c.hash[0][x] ^ c.hash[1][y] ^ c.hash[2][z]) & mask;
    return tab + (static_cast<int64_t>(h) + off[l]) * f;
  }
};

// One point on one level: its F features into ``o`` and, with ``JAC``, the features' derivatives with
// respect to the point's three coordinates into ``j`` ([F][3]). The derivative comes from the same eight
// corner rows the forward reads, so computing it here costs arithmetic, not memory traffic; a backward
// that gathered the corners again would pay the gathers twice.
template <int FIXED_F, bool JAC>
inline void encode_level(const Grid& grid, const float* p, int64_t l, int64_t f_runtime, float* o, float* j) {
  const int64_t f = FIXED_F > 0 ? FIXED_F : f_runtime;
  const Level c = locate(p, grid.scl[l]);
  const float s = grid.scl[l];  // d frac / d position
  const float fx = c.frac[0], fy = c.frac[1], fz = c.frac[2];
  const float* v[2][2][2];  // [z][y][x] corner rows
  for (int z = 0; z < 2; ++z)
    for (int y = 0; y < 2; ++y)
      for (int x = 0; x < 2; ++x) v[z][y][x] = grid.row(c, l, x, y, z);
  for (int64_t k = 0; k < f; ++k) {
    // nerfstudio's trilinear blend as three lerps (along x, then y, then z; equal to its sum of corner
    // weights times rows up to float rounding), and its derivative along each axis: the difference of
    // the two faces across that axis, blended over the other two axes.
    float a[2][2], da[2][2];  // along x, for each (z, y)
    for (int z = 0; z < 2; ++z)
      for (int y = 0; y < 2; ++y) {
        const float lo = v[z][y][0][k], hi = v[z][y][1][k];
        a[z][y] = (1.0f - fx) * lo + fx * hi;
        da[z][y] = hi - lo;
      }
    const float b0 = (1.0f - fy) * a[0][0] + fy * a[0][1], b1 = (1.0f - fy) * a[1][0] + fy * a[1][1];
    o[k] = (1.0f - fz) * b0 + fz * b1;
    if (JAC) {
      const float dx0 = (1.0f - fy) * da[0][0] + fy * da[0][1], dx1 = (1.0f - fy) * da[1][0] + fy * da[1][1];
      j[3 * k] = s * ((1.0f - fz) * dx0 + fz * dx1);
      j[3 * k + 1] = s * ((1.0f - fz) * (a[0][1] - a[0][0]) + fz * (a[1][1] - a[1][0]));
      j[3 * k + 2] = s * (b1 - b0);
    }
  }
}

template <int FIXED_F, bool JAC>
void encode_all(const Grid& grid, float* out, float* jac) {
  const int64_t levels = grid.levels, f = grid.f;
  at::parallel_for(0, grid.n, 256, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i)
      for (int64_t l = 0; l < levels; ++l) {
        const int64_t at = (i * levels + l) * f;
        encode_level<FIXED_F, JAC>(grid, grid.pos + 3 * i, l, f, out + at, JAC ? jac + 3 * at : nullptr);
      }
  });
}

template <bool JAC>
void encode(const Grid& grid, float* out, float* jac) {
  // nerfacto's grids have 2 features per level: a fixed count lets the compiler unroll the feature loops.
  if (grid.f == 2)
    encode_all<2, JAC>(grid, out, jac);
  else
    encode_all<0, JAC>(grid, out, jac);
}

}  // namespace

// positions [N, 3] in [0, 1] -> (features [N, L * F], and with ``jacobian`` d features / d positions
// [N, L * F, 3], else an empty tensor).
std::vector<torch::Tensor> hash_grid_forward(torch::Tensor positions, torch::Tensor table, torch::Tensor scalings,
                                             torch::Tensor offsets, int64_t table_size, bool jacobian) {
  const Grid grid(positions, table, scalings, offsets, table_size);
  auto out = torch::empty({grid.n, grid.levels * grid.f}, positions.options());
  if (!jacobian) {
    encode<false>(grid, out.data_ptr<float>(), nullptr);
    return {out, torch::empty({0}, positions.options())};
  }
  auto jac = torch::empty({grid.n, grid.levels * grid.f, 3}, positions.options());
  encode<true>(grid, out.data_ptr<float>(), jac.data_ptr<float>());
  return {out, jac};
}

// d loss / d positions [N, 3] from d loss / d features [N, K] and the forward's Jacobian [N, K, 3].
torch::Tensor hash_grid_backward(torch::Tensor grad_out, torch::Tensor jacobian) {
  TORCH_CHECK(grad_out.scalar_type() == torch::kFloat32 && grad_out.is_contiguous() && grad_out.dim() == 2,
              "grad_out must be a contiguous float32 tensor [N, K]");
  TORCH_CHECK(jacobian.scalar_type() == torch::kFloat32 && jacobian.is_contiguous() && jacobian.dim() == 3 &&
                  jacobian.size(0) == grad_out.size(0) && jacobian.size(1) == grad_out.size(1) &&
                  jacobian.size(2) == 3,
              "jacobian must be a contiguous float32 tensor [N, K, 3] matching grad_out");
  const int64_t n = grad_out.size(0), k = grad_out.size(1);
  auto grad = torch::empty({n, 3}, grad_out.options());
  const float* g = grad_out.data_ptr<float>();
  const float* jac = jacobian.data_ptr<float>();
  float* dst = grad.data_ptr<float>();
  at::parallel_for(0, n, 1024, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      float acc[3] = {0.0f, 0.0f, 0.0f};
      const float* gi = g + i * k;
      const float* ji = jac + i * k * 3;
      for (int64_t m = 0; m < k; ++m)
        for (int a = 0; a < 3; ++a) acc[a] += gi[m] * ji[3 * m + a];
      for (int a = 0; a < 3; ++a) dst[3 * i + a] = acc[a];
    }
  });
  return grad;
}


// A frozen proposal density field (nerfstudio's HashMLPDensityField with a torch MLP), forward only: the
// proposal networks are evaluated without gradients during inversion, and in torch each evaluation is some
// thirty tensor operations on [samples, ...] intermediates. Per sample, in this order, as nerfstudio does:
// the infinity-norm scene contraction of the position measured in ``unit``, (x + 2) / 4, the selector of
// points inside the unit cube (zeroed outside), the hash encoding, the MLP (ReLU between layers, none after),
// exp, times ``init_density``, times the selector. positions [N, 3] -> densities [N, 1].
torch::Tensor density_forward(torch::Tensor positions, double unit, torch::Tensor table, torch::Tensor scalings,
                              torch::Tensor offsets, int64_t table_size, std::vector<torch::Tensor> weights,
                              std::vector<torch::Tensor> biases, double init_density) {
  const Grid grid(positions, table, scalings, offsets, table_size);
  constexpr int64_t kMaxWidth = 256;
  TORCH_CHECK(!weights.empty() && weights.size() == biases.size(), "one bias per weight matrix");
  int64_t width = grid.levels * grid.f;
  // Each layer's weights transposed to [in][out]: the product then adds one input times a row of outputs at
  // a time, a loop over outputs the compiler vectorizes. The dot product of [out][in] is a float reduction,
  // which it may not reorder, so it ran one multiply-add after the other. The hash gathers are most of the
  // kernel's time either way (measured: 1.1-1.3x on the whole kernel).
  std::vector<torch::Tensor> transposed;
  std::vector<const float*> w, b;
  std::vector<int64_t> outs, ins;
  for (size_t k = 0; k < weights.size(); ++k) {
    TORCH_CHECK(weights[k].scalar_type() == torch::kFloat32 && weights[k].dim() == 2 &&
                    weights[k].size(1) == width && weights[k].size(0) <= kMaxWidth,
                "layer ", k, ": weights must be float32 [out <= 256, ", width, "]");
    TORCH_CHECK(biases[k].scalar_type() == torch::kFloat32 && biases[k].is_contiguous() &&
                    biases[k].numel() == weights[k].size(0),
                "layer ", k, ": bias must be contiguous float32 [out]");
    transposed.push_back(weights[k].t().contiguous());
    ins.push_back(width);
    width = weights[k].size(0);
    outs.push_back(width);
    w.push_back(transposed.back().data_ptr<float>());
    b.push_back(biases[k].data_ptr<float>());
  }
  TORCH_CHECK(width == 1, "the last layer must have one output (the density before its activation)");
  TORCH_CHECK(grid.levels * grid.f <= kMaxWidth, "at most 256 encoded features");
  auto out = torch::empty({grid.n, 1}, positions.options());
  float* dst = out.data_ptr<float>();
  const float u = static_cast<float>(unit), scale = static_cast<float>(init_density);
  at::parallel_for(0, grid.n, 256, [&](int64_t begin, int64_t end) {
    float a[kMaxWidth], h[kMaxWidth];
    for (int64_t i = begin; i < end; ++i) {
      float x[3];
      for (int c = 0; c < 3; ++c) x[c] = grid.pos[3 * i + c] / u;
      const float mag = std::max(std::fabs(x[0]), std::max(std::fabs(x[1]), std::fabs(x[2])));
      bool inside = true;
      for (int c = 0; c < 3; ++c) {
        const float contracted = mag < 1.0f ? x[c] : (2.0f - 1.0f / mag) * (x[c] / mag);
        x[c] = (contracted + 2.0f) / 4.0f;
        inside = inside && x[c] > 0.0f && x[c] < 1.0f;
      }
      if (!inside) {
        dst[i] = 0.0f;  // nerfstudio encodes the origin instead and multiplies the density by zero
        continue;
      }
      for (int64_t l = 0; l < grid.levels; ++l) {
        if (grid.f == 2)
          encode_level<2, false>(grid, x, l, 2, a + 2 * l, nullptr);
        else
          encode_level<0, false>(grid, x, l, grid.f, a + l * grid.f, nullptr);
      }
      for (size_t k = 0; k < w.size(); ++k) {
        const int64_t n_out = outs[k], n_in = ins[k];
        const float* wk = w[k];
        std::copy(b[k], b[k] + n_out, h);
        for (int64_t m = 0; m < n_in; ++m) {
          const float am = a[m];
          const float* row = wk + m * n_out;
          for (int64_t o = 0; o < n_out; ++o) h[o] += row[o] * am;
        }
        if (k + 1 < w.size())
          for (int64_t o = 0; o < n_out; ++o) h[o] = h[o] > 0.0f ? h[o] : 0.0f;
        std::copy(h, h + n_out, a);
      }
      dst[i] = scale * std::exp(a[0]);
    }
  });
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &hash_grid_forward, "hash grid encoding of a frozen table, optionally with its Jacobian");
  m.def("backward", &hash_grid_backward, "gradient with respect to the positions, from the forward's Jacobian");
  m.def("density", &density_forward, "a frozen proposal density field (contraction, hash grid, MLP, exp)");
}
