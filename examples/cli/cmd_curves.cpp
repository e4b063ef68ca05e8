// curves: several training runs' validation metrics against CPU time (or step) in one picture, and as a table.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/plot.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

std::vector<std::string> split(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream in(s);
  for (std::string item; std::getline(in, item, ',');)
    if (!item.empty()) out.push_back(item);
  return out;
}

// One run's validation lines: x (cpu_seconds of the last training line before it, or the step) and the metrics.
struct RunPoints {
  std::string name;
  std::vector<double> x;
  std::vector<json> validation;
};

RunPoints read_run(const fs::path& dir, bool by_step) {
  const fs::path log = dir / "log.jsonl";
  std::ifstream f(log);
  require(f.good(), "curves: cannot read '", log.string(), "' (a `flexsplat train` run folder?)");
  RunPoints r;
  r.name = dir.filename().string();
  if (r.name.empty()) r.name = dir.parent_path().filename().string();
  double cpu = 0;
  std::size_t line_no = 0;
  for (std::string line; std::getline(f, line);) {
    ++line_no;
    json j;
    try {
      j = json::parse(line);
    } catch (const json::exception&) {
      fail("curves: '", log.string(), "' line ", line_no, " is not JSON");
    }
    if (!j.is_object() || !j.contains("step")) continue;
    if (!j.contains("validation")) {
      cpu = j.value("cpu_seconds", cpu);
      continue;
    }
    r.x.push_back(by_step ? j["step"].get<double>() : cpu);
    r.validation.push_back(j["validation"]);
  }
  require(!r.x.empty(), "curves: '", log.string(), "' has no validation line");
  require(by_step || cpu > 0, "curves: '", log.string(), "' has no cpu_seconds (made before they were logged); use --x step");
  return r;
}

int curves(Args args) {
  std::string metrics_text = "rotation_deg", sets_text, out, x_axis = "cpu";
  take_option(args, "--metrics", metrics_text);
  take_option(args, "--sets", sets_text);
  take_option(args, "--out", out);
  take_option(args, "--x", x_axis);
  require(x_axis == "cpu" || x_axis == "step", "curves: --x '", x_axis, "' is neither 'cpu' nor 'step'");
  require(!args.empty(), "curves needs at least one RUN_DIR");
  for (const auto& a : args) require(a.rfind("--", 0) != 0, "curves: unknown option '", a, "'");
  const std::vector<std::string> metrics = split(metrics_text);
  require(!metrics.empty(), "curves: --metrics is empty");
  std::vector<RunPoints> runs;
  for (const auto& a : args) runs.push_back(read_run(a, x_axis == "step"));
  std::vector<std::string> sets = split(sets_text);
  if (sets.empty())
    for (const auto& [name, v] : runs[0].validation.back().items()) sets.push_back(name);

  const image::Rgb8 palette[] = {{31, 119, 180}, {214, 39, 40}, {44, 160, 44}, {148, 103, 189}, {255, 127, 14},
                                 {23, 190, 207}, {140, 86, 75}, {227, 119, 194}};
  std::vector<Tensor<std::uint8_t, 3>> panels;
  image::PlotOptions o;
  o.width = 900, o.height = 320;
  o.x_label = x_axis == "cpu" ? "CPU seconds" : "step";
  for (const auto& set : sets)
    for (const auto& metric : metrics) {
      std::vector<image::PlotSeries> series;
      std::printf("%s %s\n", set.c_str(), metric.c_str());
      for (std::size_t r = 0; r < runs.size(); ++r) {
        image::PlotSeries s{runs[r].name, {}, {}, palette[r % 8]};
        for (std::size_t i = 0; i < runs[r].x.size(); ++i) {
          const json& v = runs[r].validation[i];
          if (!v.contains(set) || !v[set].contains(metric) || !v[set][metric].is_number()) continue;
          s.x.push_back(runs[r].x[i]), s.y.push_back(v[set][metric].get<double>());
        }
        if (s.x.empty()) continue;
        std::printf("  %-32s", runs[r].name.c_str());
        const std::size_t n = s.x.size();
        for (std::size_t i : {std::size_t(0), n / 4, n / 2, 3 * n / 4, n - 1})
          std::printf("  %7.0f: %-8.3g", s.x[i], s.y[i]);
        std::printf("\n");
        series.push_back(std::move(s));
      }
      if (series.empty()) continue;
      o.title = set + ": " + metric;
      panels.push_back(image::plot_lines(series, o));
    }
  require(!panels.empty(), "curves: no run has any of the metrics ", metrics_text, " in the sets asked for");
  if (!out.empty()) {
    Tensor<std::uint8_t, 3> all(Shape<3>{static_cast<index_t>(panels.size()) * o.height, o.width, 3});
    for (std::size_t i = 0; i < panels.size(); ++i)
      std::copy(panels[i].data(), panels[i].data() + panels[i].size(), all.data() + static_cast<index_t>(i) * panels[i].size());
    image::write_png(out, all);
  }
  return 0;
}

const RegisterCommand registered_cmd_curves(
    "curves", {"validation metrics of training runs against CPU time or step: one panel per set and metric",
               "RUN_DIR... [--metrics rotation_deg,rra30,...] [--sets objects,procedural,...] [--x cpu|step]\n"
               "  [--out curves.png]\n"
               "  reads each RUN_DIR/log.jsonl of `flexsplat train`; x is the run's own CPU seconds (cpu_seconds of the\n"
               "  training line before each validation) or the step; prints each series at 0, 1/4, 1/2, 3/4 and the end\n"
               "  metrics: any validation key (rotation_deg, rra15, rra30, chance_rotation_deg, points_rotation_deg,\n"
               "  matches_rotation_deg, matches_rra30, match_accuracy, match_accuracy_4px, match_accuracy_0_30 (_30_60,\n"
               "  _60_90, _90_180: by the pair's true baseline), pairs_gt_depth_rra15_0_30 (likewise: view pairs whose own\n"
               "  fit with the renderer's depth is within 15 deg), matches_gt_depth_rotation_deg,\n"
               "  matches_oracle_rotation_deg, matches_oracle_rra15, psnr, ssim, depth_rel, depth_shape_rel);\n"
               "  sets default to the first run's",
               curves});

}  // namespace
}  // namespace flexsplat::cli
