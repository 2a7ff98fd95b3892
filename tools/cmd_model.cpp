// `mocap model show M.json`, `mocap model diff A.json B.json [--json]` and
// `mocap model default --out M.json [--height H]`: a readable summary of a model file, the
// gauge-free comparison of two models (model/compare.h), A the reference, and the default
// full-body model (model/default_model.h) written out.
// Exit codes: 0 done, 1 a file could not be loaded or the models differ in topology, 2 usage.
#include <cmath>
#include <cstdio>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "model/compare.h"
#include "model/default_model.h"
#include "model/model.h"
#include "formats/osim.h"
#include "model/model_io.h"
#include "tools/command.h"

namespace mocap::tools {
namespace {

constexpr int kExitFailure = 1;
constexpr int kExitUsage = 2;

struct ModelOptions {
  std::vector<std::string> files;
  bool json = false;
};

// CLI11 reports its own parse errors with codes >= 100; usage errors of these commands are
// checked here instead (arguments optional, extras allowed) so that they exit with 2.
int UsageError(const CLI::App* command, const std::string& message) {
  std::string name = command->get_name();
  for (const CLI::App* p = command->get_parent(); p && p->get_parent(); p = p->get_parent())
    name = p->get_name() + " " + name;
  std::fprintf(stderr, "mocap %s: %s\n%s", name.c_str(), message.c_str(),
               command->help().c_str());
  return kExitUsage;
}

bool CheckArguments(const CLI::App* command, const ModelOptions& options, size_t want,
                    int* exit_code) {
  if (!command->remaining().empty()) {
    *exit_code = UsageError(command, "unexpected argument '" + command->remaining().front() + "'");
    return false;
  }
  if (options.files.size() != want) {
    *exit_code = UsageError(command, "expected " + std::to_string(want) + " model file" +
                                         (want > 1 ? "s" : "") + ", got " +
                                         std::to_string(options.files.size()));
    return false;
  }
  return true;
}

bool Load(const char* command, const std::string& path, Model* model) {
  Status s;
  if (path.size() > 5 && path.compare(path.size() - 5, 5, ".osim") == 0) {
    formats::OsimImport imported;
    s = formats::ImportOsim(path, &imported);
    if (s.ok()) *model = std::move(imported.model);
  } else {
    s = LoadModelJson(path, model);
  }
  if (s.ok()) return true;
  // LoadModelJson's messages start with the path; make sure the file is named either way.
  const std::string& m = s.message();
  std::fprintf(stderr, "mocap model %s: %s\n", command,
               m.rfind(path, 0) == 0 ? m.c_str() : (path + ": " + m).c_str());
  return false;
}

std::string Vec(Eigen::Vector3d v, int decimals) {
  for (int i = 0; i < 3; ++i)  // no "-0.0000"
    if (std::abs(v[i]) < 0.5 * std::pow(10.0, -decimals)) v[i] = 0.0;
  char buf[96];
  std::snprintf(buf, sizeof buf, "(%.*f, %.*f, %.*f)", decimals, v.x(), decimals, v.y(), decimals,
                v.z());
  return buf;
}

int RunShow(const std::string& path) {
  Model model;
  if (!Load("show", path, &model)) return kExitFailure;
  int groups[kNumParameterGroups] = {0, 0, 0, 0};
  for (const auto& p : model.parameters()) ++groups[static_cast<int>(p.group)];
  std::printf("model '%s' (%s)\n", model.name().c_str(), path.c_str());
  std::printf("  %d segments, %d joints, %d coordinates, %d markers, %d parameters\n",
              model.num_segments(), model.num_joints(), model.num_coordinates(),
              model.num_markers(), model.num_parameters());
  std::printf("  parameters per group:");
  for (int g = 0; g < kNumParameterGroups; ++g)
    std::printf(" %s %d%s", ToString(static_cast<ParameterGroup>(g)), groups[g],
                g + 1 < kNumParameterGroups ? "," : "\n");

  std::printf("\nsegments (scale; markers, * optional):\n");
  for (int s = 0; s < model.num_segments(); ++s) {
    std::string markers;
    int n = 0;
    for (const auto& m : model.markers())
      if (m.segment == s) {
        markers += " " + m.name + (m.optional ? "*" : "");
        ++n;
      }
    std::printf("  %-14s scale %.4f  %d marker%s%s%s\n", model.segments()[s].name.c_str(),
                model.segments()[s].scale, n, n == 1 ? "" : "s", n ? ":" : "", markers.c_str());
  }

  std::printf("\njoints (centre in the parent's unscaled frame, m; axes in the frame before "
              "each element):\n");
  for (const auto& j : model.joints()) {
    const std::string parent = j.parent < 0 ? "ground" : model.segments()[j.parent].name;
    std::printf("  %-14s %-9s %s -> %s  centre %s\n", j.name.c_str(), ToString(j.type),
                parent.c_str(), model.segments()[j.child].name.c_str(), Vec(j.centre, 4).c_str());
    if (!j.orientation.isIdentity(0)) {
      const Eigen::AngleAxisd aa(j.orientation);
      std::printf("  %-14s orientation %.2f deg about %s\n", "", aa.angle() * 180.0 / M_PI,
                  Vec(aa.axis(), 3).c_str());
    }
    for (const auto& el : j.elements) {
      const std::string coord =
          el.coordinate >= 0 ? model.coordinates()[el.coordinate].name : std::string("-");
      std::string fn;
      if (el.function.kind == CoordinateFunction::Kind::kLinear) {
        char buf[64];
        std::snprintf(buf, sizeof buf, "  v = %g z %+g", el.function.slope, el.function.offset);
        fn = buf;
      } else if (el.function.kind == CoordinateFunction::Kind::kConstant) {
        char buf[64];
        std::snprintf(buf, sizeof buf, "  constant %g", el.function.offset);
        fn = buf;
      }
      std::printf("  %-14s   %-11s %-20s axis %s%s%s\n", "",
                  el.kind == ElementKind::kRotation ? "rotation" : "translation", coord.c_str(),
                  Vec(el.axis, 4).c_str(), el.fitted_axis ? "  fitted" : "", fn.c_str());
    }
  }
  return 0;
}

std::string Number(double v, const char* format) {
  if (!std::isfinite(v)) return "-";
  char buf[64];
  std::snprintf(buf, sizeof buf, format, v);
  return buf;
}

void PrintStats(const char* what, const ErrorStats& s, const char* unit, const char* of) {
  std::printf("  %-22s max %9.4f %-3s  rms %9.4f %-3s  (%d %s)\n", what, s.max, unit, s.rms, unit,
              s.count, of);
}

int RunDiff(const ModelOptions& options) {
  const std::string& path_a = options.files[0];
  const std::string& path_b = options.files[1];
  Model a, b;
  if (!Load("diff", path_a, &a) || !Load("diff", path_b, &b)) return kExitFailure;
  ModelComparison c;
  if (Status s = CompareModels(a, b, &c); !s) {
    std::fprintf(stderr, "mocap model diff: %s (A) and %s (B) differ in topology: %s\n",
                 path_a.c_str(), path_b.c_str(), s.message().c_str());
    return kExitFailure;
  }
  if (options.json) {
    std::printf("%s\n", ComparisonToJsonString(c).c_str());
    return 0;
  }

  std::printf("A (reference): %s\nB:             %s\n", path_a.c_str(), path_b.c_str());
  std::printf("\njoints (hinge centres: distance across the axis only)\n");
  std::printf("  %-14s %-9s %10s %10s  %s\n", "joint", "type", "centre mm", "axis deg",
              "centre aligned on");
  for (const auto& j : c.joints)
    std::printf("  %-14s %-9s %10s %10s  %s\n", j.joint.c_str(), ToString(j.type),
                Number(j.centre_error_mm, "%.3f").c_str(), Number(j.axis_error_deg, "%.3f").c_str(),
                j.basis.c_str());

  std::printf("\nsegment lengths (to hinge axes where an end is a hinge)\n");
  std::printf("  %-30s %10s %10s %9s\n", "length", "A mm", "B mm", "error %");
  for (const auto& s : c.segments)
    std::printf("  %-30s %10.2f %10.2f %9s\n", s.name.c_str(), s.length_a_mm, s.length_b_mm,
                Number(s.error_pct, "%+.3f").c_str());

  std::printf("\nmarkers (after their segment's rigid alignment; 'unaligned': the segment has "
              "< 3 markers,\ncompared in its own frame, which a gauge can move)\n");
  std::printf("  %-8s %-14s %10s\n", "marker", "segment", "error mm");
  for (const auto& m : c.markers)
    std::printf("  %-8s %-14s %10.3f%s\n", m.marker.c_str(), m.segment.c_str(), m.error_mm,
                m.aligned ? "" : "  unaligned");
  auto list = [](const char* what, const std::vector<std::string>& names) {
    if (names.empty()) return;
    std::printf("  %s (ignored):", what);
    for (const auto& n : names) std::printf(" %s", n.c_str());
    std::printf("\n");
  };
  list("only in A", c.markers_only_in_a);
  list("only in B", c.markers_only_in_b);

  std::printf("\nsummary\n");
  PrintStats("joint centre error", c.joint_centre_error_mm, "mm", "joints");
  PrintStats("axis error", c.axis_error_deg, "deg", "axes");
  PrintStats("segment length error", c.segment_length_error_pct, "%", "lengths");
  PrintStats("marker error", c.marker_error_mm, "mm", "markers");
  return 0;
}

const CommandRegistrar registrar("model", [](CLI::App& app, int* exit_code) {
  CLI::App* model = app.add_subcommand("model", "Inspect and compare body model files");
  CLI::App* show = model->add_subcommand("show", "Summarise a model file");
  CLI::App* diff = model->add_subcommand(
      "diff", "Compare model B with reference A by what marker data determines (gauge-free)");
  CLI::App* def = model->add_subcommand(
      "default", "Write the default full-body model (Plug-in Gait markers, Z up) as JSON");
  auto default_out = std::make_shared<std::string>();
  auto default_height = std::make_shared<double>(1.75);
  def->add_option("--out", *default_out, "Model file to write (.json)")->required();
  def->add_option("--height", *default_height, "Stature (m) the segments are scaled to")
      ->capture_default_str()
      ->check(CLI::Range(0.5, 2.5));
  def->callback([default_out, default_height, exit_code] {
    if (Status s = SaveModelJson(*default_out, DefaultFullBodyModel(*default_height)); !s) {
      std::fprintf(stderr, "mocap model default: %s\n", s.message().c_str());
      *exit_code = 1;
    }
  });
  auto show_options = std::make_shared<ModelOptions>();
  auto diff_options = std::make_shared<ModelOptions>();
  show->add_option("model", show_options->files, "Model file (JSON)");
  show->allow_extras();
  diff->add_option("models", diff_options->files, "A B: reference and compared model (.json or OpenSim .osim)");
  diff->add_flag("--json", diff_options->json, "Print one JSON object instead of tables");
  diff->allow_extras();

  show->callback([show, show_options, exit_code] {
    if (CheckArguments(show, *show_options, 1, exit_code))
      *exit_code = RunShow(show_options->files[0]);
  });
  diff->callback([diff, diff_options, exit_code] {
    if (CheckArguments(diff, *diff_options, 2, exit_code)) *exit_code = RunDiff(*diff_options);
  });
  model->callback([model, exit_code] {
    if (model->get_subcommands().empty()) *exit_code = UsageError(model, "expected show, diff or default");
  });
});

}  // namespace
}  // namespace mocap::tools
