// nerfstudio's multi-resolution hash encoding, forward and backward with respect to the positions, for
// frozen tables on the CPU. One pass per point and level does what the torch version spreads over a
// dozen tensor operations (scale, floor, hash eight corners, gather, blend), so nothing is written to
// memory between them. Same hash, same table layout, same corner weights as
// nerfstudio.field_components.encodings.HashEncoding.pytorch_fwd.
#include <torch/extension.h>

#include <ATen/Parallel.h>
#include <cmath>
#include <cstdint>

namespace {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;

struct Level {
  float weight[3][2]; // [axis][floor corner, ceil corner]
  uint32_t hash[3][2];
};

inline Level locate(const float* p, float scaling) {
  Level c;
  for (int a = 0; a < 3; ++a) {
    const float x = p[a] * scaling;
    const float lower = std::floor(x);
    const float frac = x - lower;
    c.weight[a][0] = 1.0f - frac;
    c.weight[a][1] = frac;
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

}  // namespace

// positions [N, 3] in [0, 1] -> features [N, L * F]
torch::Tensor hash_grid_forward(torch::Tensor positions, torch::Tensor table, torch::Tensor scalings,
                                torch::Tensor offsets, int64_t table_size) {
  const Grid grid(positions, table, scalings, offsets, table_size);
  const int64_t levels = grid.levels, f = grid.f;
  auto out = torch::empty({grid.n, levels * f}, positions.options());
  float* dst = out.data_ptr<float>();
  at::parallel_for(0, grid.n, 256, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      for (int64_t l = 0; l < levels; ++l) {
        const Level c = locate(grid.pos + 3 * i, grid.scl[l]);
        float* o = dst + (i * levels + l) * f;
        for (int64_t k = 0; k < f; ++k) o[k] = 0.0f;
        for (int z = 0; z < 2; ++z)
          for (int y = 0; y < 2; ++y)
            for (int x = 0; x < 2; ++x) {
              const float w = c.weight[2][z] * (c.weight[1][y] * c.weight[0][x]);
              const float* row = grid.row(c, l, x, y, z);
              for (int64_t k = 0; k < f; ++k) o[k] += w * row[k];
            }
      }
    }
  });
  return out;
}

// d loss / d positions [N, 3] from d loss / d features [N, L * F]; the table gets no gradient.
torch::Tensor hash_grid_backward(torch::Tensor grad_out, torch::Tensor positions, torch::Tensor table,
                                 torch::Tensor scalings, torch::Tensor offsets, int64_t table_size) {
  const Grid grid(positions, table, scalings, offsets, table_size);
  const int64_t levels = grid.levels, f = grid.f;
  TORCH_CHECK(grad_out.scalar_type() == torch::kFloat32 && grad_out.is_contiguous() &&
                  grad_out.numel() == grid.n * levels * f,
              "grad_out must be a contiguous float32 tensor [N, L * F]");
  auto grad = torch::zeros({grid.n, 3}, positions.options());
  const float* g = grad_out.data_ptr<float>();
  float* dst = grad.data_ptr<float>();
  at::parallel_for(0, grid.n, 256, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      float acc[3] = {0.0f, 0.0f, 0.0f};
      for (int64_t l = 0; l < levels; ++l) {
        const Level c = locate(grid.pos + 3 * i, grid.scl[l]);
        const float* gl = g + (i * levels + l) * f;
        float d[3] = {0.0f, 0.0f, 0.0f};  // d features . grad / d frac, per axis
        for (int z = 0; z < 2; ++z)
          for (int y = 0; y < 2; ++y)
            for (int x = 0; x < 2; ++x) {
              const float* row = grid.row(c, l, x, y, z);
              float dot = 0.0f;
              for (int64_t k = 0; k < f; ++k) dot += gl[k] * row[k];
              // The weight is w_x * w_y * w_z with w = 1 - frac on the floor corner and frac on the ceil one.
              d[0] += (x ? 1.0f : -1.0f) * c.weight[1][y] * c.weight[2][z] * dot;
              d[1] += (y ? 1.0f : -1.0f) * c.weight[0][x] * c.weight[2][z] * dot;
              d[2] += (z ? 1.0f : -1.0f) * c.weight[0][x] * c.weight[1][y] * dot;
            }
        for (int a = 0; a < 3; ++a) acc[a] += grid.scl[l] * d[a];
      }
      for (int a = 0; a < 3; ++a) dst[3 * i + a] = acc[a];
    }
  });
  return grad;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &hash_grid_forward, "hash grid encoding, frozen table");
  m.def("backward", &hash_grid_backward, "gradient of the hash grid encoding with respect to the positions");
}
