// Run time against error of geometry::cameras_from_orbit_search given the renderer's silhouettes and depth (the
// ceiling of the search: what it finds when the model's predictions are exact) on object folders: random input view
// sets of each count, median and mean relative rotation error, the sets within 15 degrees, seconds per set.
// Usage: orbit_search [--size 56] [--sets 2] [--seed 7] [--counts 2,3,4,8] OBJECT_DIR...
//   e.g. `build/bench/orbit_search ../shared/data/objects/*`
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <numeric>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/geometry/orbit_search.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/model/evaluate.hpp"
#include "flexsplat/model/frames.hpp"

using namespace flexsplat;

int main(int argc, char** argv) try {
  int size = 56, sets = 2;
  unsigned seed = 7;
  std::vector<int> counts{2, 3, 4, 8};
  std::vector<std::string> dirs;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const bool more = i + 1 < argc;
    if (a == "--size" && more) size = std::stoi(argv[++i]);
    else if (a == "--sets" && more) sets = std::stoi(argv[++i]);
    else if (a == "--seed" && more) seed = static_cast<unsigned>(std::stoul(argv[++i]));
    else if (a == "--counts" && more) {
      counts.clear();
      std::string s = argv[++i];
      for (std::size_t p = 0; p < s.size();) {
        const std::size_t q = s.find(',', p);
        counts.push_back(std::stoi(s.substr(p, q - p)));
        p = q == std::string::npos ? s.size() : q + 1;
      }
    } else dirs.push_back(a);
  }
  require(!dirs.empty() && size >= 8 && sets >= 1, "usage: orbit_search [--size N] [--sets N] [--seed N] [--counts 2,3,4,8] OBJECT_DIR...");
  std::vector<data::ObjectRecord> objects;
  for (const auto& d : dirs) objects.push_back(data::load_object(d));
  std::mt19937 rng(seed);
  std::printf("| views | sets | median error | mean error | within 15° | seconds per set |\n|---|---|---|---|---|---|\n");
  for (const int n : counts) {
    std::vector<double> errors;
    double seconds = 0;
    for (const auto& rec : objects) {
      const int frames = static_cast<int>(rec.frames.size());
      require(n >= 2 && n <= frames, "orbit_search: ", n, " views asked of ", rec.dir.string(), " (", frames, " frames)");
      for (int s = 0; s < sets; ++s) {
        std::vector<int> all(static_cast<std::size_t>(frames));
        std::iota(all.begin(), all.end(), 0);
        std::shuffle(all.begin(), all.end(), rng);
        const std::vector<int> in(all.begin(), all.begin() + n);
        model::PosedViews pv = model::posed_views(rec, in, size, size);
        const std::size_t px = static_cast<std::size_t>(size) * static_cast<std::size_t>(size);
        std::vector<float> depth(static_cast<std::size_t>(n) * px), K(9 * static_cast<std::size_t>(n)), fg(depth.size());
        for (int v = 0; v < n; ++v) {  // nearest source pixel of each view pixel's centre (the views are square)
          const Tensor<double, 2> d = image::read_depth_png<double>(rec.frames[static_cast<std::size_t>(in[static_cast<std::size_t>(v)])].depth, rec.depth_scale);
          const index_t H = d.shape(0), W = d.shape(1);
          for (int y = 0; y < size; ++y)
            for (int x = 0; x < size; ++x) {
              const index_t sy = std::min<index_t>(H - 1, static_cast<index_t>((y + 0.5) * static_cast<double>(H) / size));
              const index_t sx = std::min<index_t>(W - 1, static_cast<index_t>((x + 0.5) * static_cast<double>(W) / size));
              depth[static_cast<std::size_t>(v) * px + static_cast<std::size_t>(y * size + x)] = static_cast<float>(d(sy, sx));
            }
        }
        for (std::size_t i = 0; i < fg.size(); ++i) fg[i] = depth[i] > 0 && pv.photos.alpha[i] > 0.5f ? 1.f : 0.f;
        model::intrinsics_to_vggt(K.data(), pv.photos.K.data(), n);
        std::vector<float> E(12 * static_cast<std::size_t>(n));
        const auto t0 = std::chrono::steady_clock::now();
        geometry::cameras_from_orbit_search<float>(E.data(), pv.photos.images.data(), fg.data(), depth.data(), K.data(), n,
                                                   size, size);
        seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        const std::vector<double> pred(E.begin(), E.end()), gt(pv.w2c.begin(), pv.w2c.end());
        double e = 0;
        for (int v = 1; v < n; ++v) e += model::relative_rotation_error_deg(pred.data(), pred.data() + 12 * v, gt.data(), gt.data() + 12 * v);
        errors.push_back(e / (n - 1));
      }
    }
    std::vector<double> sorted = errors;
    std::sort(sorted.begin(), sorted.end());
    const double median = sorted.size() % 2 ? sorted[sorted.size() / 2]
                                             : 0.5 * (sorted[sorted.size() / 2 - 1] + sorted[sorted.size() / 2]);
    const double mean = std::accumulate(sorted.begin(), sorted.end(), 0.0) / static_cast<double>(sorted.size());
    const auto within = std::count_if(errors.begin(), errors.end(), [](double e) { return e <= 15; });
    std::printf("| %d | %zu | %.1f° | %.1f° | %lld / %zu | %.2f |\n", n, errors.size(), median, mean,
                static_cast<long long>(within), errors.size(), seconds / static_cast<double>(errors.size()));
    std::fflush(stdout);
  }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "orbit_search: %s\n", e.what());
  return 1;
}
