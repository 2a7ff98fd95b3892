#include "report/fit_report_html.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <set>

#include "model/kinematics.h"
#include "model/model_io.h"
#include "report/svg_writer.h"

namespace mocap::report {
namespace {

using nlohmann::json;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

std::string Fixed(double v, int decimals) {
  if (!std::isfinite(v)) return "–";
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

std::string Esc(const std::string& s) { return EscapeXml(s); }

double Number(const json& j, const char* key, double fallback = kNaN) {
  auto it = j.find(key);
  return it != j.end() && it->is_number() ? it->get<double>() : fallback;
}

const char* kStyle = R"css(
:root { --fit: #1f5fbf; --nom: #8a8f98; --bad: #c0262d; --ok: #1d7d3a; --grey: #9aa0a6; }
* { box-sizing: border-box; }
body { font: 14px/1.45 system-ui, "Segoe UI", "DejaVu Sans", Arial, sans-serif; color: #1d2125;
       margin: 0 auto; max-width: 1200px; padding: 16px 24px; background: #fff; }
h1 { font-size: 22px; margin: 4px 0 2px; }
h2 { font-size: 17px; margin: 22px 0 6px; border-bottom: 1px solid #d6d9dd; padding-bottom: 3px; }
.sub { color: #5f6670; margin: 0 0 10px; }
.cards { display: flex; flex-wrap: wrap; gap: 10px; margin: 10px 0; }
.card { border: 1px solid #d6d9dd; border-radius: 6px; padding: 6px 12px; min-width: 130px; }
.card .k { font-size: 12px; color: #5f6670; }
.card .v { font-size: 20px; font-weight: 600; }
.alert { border-left: 5px solid var(--bad); background: #fdecec; padding: 8px 12px; margin: 8px 0; }
.note { border-left: 5px solid var(--grey); background: #f2f3f5; padding: 8px 12px; margin: 8px 0; }
.good { border-left: 5px solid var(--ok); background: #e9f6ee; padding: 8px 12px; margin: 8px 0; }
table { border-collapse: collapse; font-size: 13px; margin: 4px 0; }
th, td { padding: 3px 8px; border-bottom: 1px solid #e4e6e9; text-align: right; }
th:first-child, td:first-child { text-align: left; }
th { background: #f5f6f7; font-weight: 600; }
tr.undetermined td, li.undetermined { color: var(--grey); font-style: italic; }
td.functional { text-align: left; }
span.notexcited { color: var(--grey); font-style: italic; }
td.bad, span.bad { color: var(--bad); font-weight: 600; }
td.okc { color: var(--ok); }
.views { display: flex; flex-wrap: wrap; gap: 8px; }
.views figure { margin: 0; }
figcaption { font-size: 12px; color: #5f6670; text-align: center; }
svg { max-width: 100%; height: auto; font-family: inherit; }
svg .frame { fill: #fbfbfc; stroke: #d6d9dd; }
svg .seg.fitted { stroke: var(--fit); stroke-width: 2.2; }
svg .seg.nominal { stroke: var(--nom); stroke-width: 1.4; stroke-dasharray: 4 3; }
svg .joint.fitted { fill: var(--fit); }
svg .joint.nominal { fill: none; stroke: var(--nom); stroke-width: 1.2; }
svg .axis.fitted { stroke: #e07b00; stroke-width: 1.8; }
svg .axis.nominal { stroke: #c9b28a; stroke-width: 1.2; stroke-dasharray: 3 2; }
svg .sd { fill: rgba(31,95,191,.18); stroke: var(--fit); stroke-width: .8; }
svg .sd.undetermined { fill: rgba(154,160,166,.25); stroke: var(--grey); }
svg .marker { fill: #6b7480; }
svg .marker.outlier { fill: var(--bad); }
svg .lbl { font-size: 11px; fill: #3c4249; }
svg .lbl.small { font-size: 9.5px; }
svg .tick { stroke: #e1e4e8; stroke-width: 1; }
svg .axisline { stroke: #9aa0a6; stroke-width: 1; }
svg .curve { fill: none; stroke: var(--fit); stroke-width: 1.3; }
svg .curve.alt { stroke: #e07b00; }
svg .mean { stroke: var(--bad); stroke-width: 1; stroke-dasharray: 4 3; }
svg .bar { fill: var(--fit); }
svg .bar.outlier { fill: var(--bad); }
svg .band { fill: #eef1f5; }
svg .phase { fill: #dfe6f0; }
svg .phase.alt { fill: #e9e2d3; }
svg .required { fill: #d6dbe2; }
svg .reached { fill: var(--fit); }
svg .reached.fail { fill: var(--bad); }
svg .dot { fill: var(--fit); }
.legend span { display: inline-block; margin-right: 14px; font-size: 12px; }
.sw { display: inline-block; width: 18px; height: 3px; vertical-align: middle; margin-right: 4px; }
.two { display: flex; flex-wrap: wrap; gap: 16px; }
code { font-size: 12px; }
@media print {
  @page { size: A4; margin: 12mm; }
  body { font-size: 9pt; max-width: none; padding: 0; }
  h2 { break-after: avoid; }
  section, figure, table { break-inside: avoid; }
  .card .v { font-size: 14pt; }
}
)css";

// ---- skeleton geometry -----------------------------------------------------------------------

struct JointDrawing {
  std::string name;
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();  // lab, default pose
  Eigen::Vector3d parent_origin = Eigen::Vector3d::Zero();
  bool has_parent = false;
  Eigen::Matrix3d parent_axes = Eigen::Matrix3d::Identity();  // s_P R_P: parent (unscaled) -> lab
  std::vector<Eigen::Vector3d> axes;                          // fitted axes, lab
};

struct ModelDrawing {
  std::vector<JointDrawing> joints;
  std::vector<std::pair<std::string, Eigen::Vector3d>> markers;
};

ModelDrawing DrawModel(const Model& model) {
  ModelDrawing out;
  const Geometry g(model);
  ModelData d(model);
  ForwardKinematics(model, g, model.DefaultCoordinates(), &d);
  for (int j = 0; j < model.num_joints(); ++j) {
    const Joint& jt = model.joints()[j];
    JointDrawing jd;
    jd.name = jt.name;
    jd.centre = JointCentre(model, d, j);
    if (jt.parent >= 0) {
      jd.has_parent = true;
      jd.parent_origin = d.segment_position[jt.parent];
      jd.parent_axes = g.scale[jt.parent] * d.segment_rotation[jt.parent];
    }
    for (size_t e = 0; e < jt.elements.size(); ++e)
      if (jt.elements[e].fitted_axis && jt.elements[e].kind == ElementKind::kRotation)
        jd.axes.push_back(d.element_rotation[j][e] * g.axis[j][e]);
    out.joints.push_back(jd);
  }
  Eigen::Matrix3Xd markers;
  MarkerPositions(model, g, d, &markers);
  for (int m = 0; m < model.num_markers(); ++m)
    out.markers.emplace_back(model.markers()[m].name, markers.col(m));
  return out;
}

double Dot(const double a[3], const Eigen::Vector3d& p) { return a[0] * p.x() + a[1] * p.y() + a[2] * p.z(); }

// Per joint: the report's standard deviations of its centre (x, y, z, metres, unscaled in the
// parent), and whether any of them is undetermined.
struct CentreSd {
  Eigen::Vector3d sd = Eigen::Vector3d::Constant(kNaN);
  bool fitted = false;
  bool undetermined = false;
};

std::map<std::string, CentreSd> CentreSds(const json& report) {
  std::map<std::string, CentreSd> out;
  std::set<std::string> undetermined;
  for (const auto& u : report.value("undetermined", json::array()))
    if (u.is_string()) undetermined.insert(u.get<std::string>());
  static const char* kXyz[3] = {"x", "y", "z"};
  for (const auto& p : report.value("parameters", json::array())) {
    const std::string name = p.value("name", "");
    const size_t at = name.rfind(".centre.");
    if (at == std::string::npos || name.size() != at + 9) continue;
    const std::string joint = name.substr(0, at);
    for (int k = 0; k < 3; ++k)
      if (name.back() == kXyz[k][0]) {
        CentreSd& c = out[joint];
        c.sd[k] = Number(p, "std");
        c.fitted = true;
        c.undetermined |= undetermined.count(name) > 0 || !p.value("determined", true);
      }
  }
  // A joint the fit held (its trials do not move it) has no estimate, only the listing.
  for (const std::string& name : undetermined) {
    const size_t at = name.rfind(".centre.");
    if (at != std::string::npos && name.size() == at + 9) out[name.substr(0, at)].undetermined = true;
  }
  return out;
}

std::string SkeletonViewsHtml(const FitReportPage& in, const std::set<std::string>& outliers) {
  const ModelDrawing fit = DrawModel(in.fitted), nom = DrawModel(in.initial);
  const auto sds = CentreSds(in.report);
  constexpr double kWidth = 360, kHeight = 440, kPad = 28;
  // One scale for all three views, so lengths compare across them.
  double scale = std::numeric_limits<double>::infinity();
  std::vector<std::array<double, 4>> bounds;  // per view: min h, max h, min v, max v
  for (const OrthographicView& view : SkeletonViews()) {
    std::array<double, 4> b = {1e9, -1e9, 1e9, -1e9};
    auto extend = [&](const Eigen::Vector3d& p) {
      b[0] = std::min(b[0], Dot(view.h, p));
      b[1] = std::max(b[1], Dot(view.h, p));
      b[2] = std::min(b[2], Dot(view.v, p));
      b[3] = std::max(b[3], Dot(view.v, p));
    };
    for (const ModelDrawing* m : {&fit, &nom}) {
      for (const auto& j : m->joints) extend(j.centre);
      for (const auto& [name, p] : m->markers) extend(p);
    }
    scale = std::min({scale, (kWidth - 2 * kPad) / std::max(b[1] - b[0], 1e-3),
                      (kHeight - 2 * kPad) / std::max(b[3] - b[2], 1e-3)});
    bounds.push_back(b);
  }
  std::string html = "<div class=\"views\">";
  for (size_t vi = 0; vi < SkeletonViews().size(); ++vi) {
    const OrthographicView& view = SkeletonViews()[vi];
    const auto& b = bounds[vi];
    const double ox = kWidth / 2 - scale * (b[0] + b[1]) / 2;
    const double oy = kHeight / 2 + scale * (b[2] + b[3]) / 2;
    auto X = [&](const Eigen::Vector3d& p) { return ox + scale * Dot(view.h, p); };
    auto Y = [&](const Eigen::Vector3d& p) { return oy - scale * Dot(view.v, p); };
    SvgWriter svg(kWidth, kHeight, "skeleton", std::string(view.name) + " view of the fitted skeleton");
    svg.Rect(0.5, 0.5, kWidth - 1, kHeight - 1, "frame");
    svg.BeginGroup("view", {{"data-view", view.name}, {"data-scale", SvgNumber(scale, 6)},
                            {"data-ox", SvgNumber(ox, 6)}, {"data-oy", SvgNumber(oy, 6)},
                            {"data-h", SvgNumber(view.h[0], 0) + "," + SvgNumber(view.h[1], 0) + "," + SvgNumber(view.h[2], 0)},
                            {"data-v", SvgNumber(view.v[0], 0) + "," + SvgNumber(view.v[1], 0) + "," + SvgNumber(view.v[2], 0)}});
    for (const auto& [drawing, cls] : {std::pair{&nom, "nominal"}, std::pair{&fit, "fitted"}}) {
      for (const JointDrawing& j : drawing->joints)
        if (j.has_parent)
          svg.Line(X(j.parent_origin), Y(j.parent_origin), X(j.centre), Y(j.centre),
                   std::string("seg ") + cls);
      for (const JointDrawing& j : drawing->joints)
        for (const Eigen::Vector3d& a : j.axes) {
          const Eigen::Vector3d p0 = j.centre - 0.06 * a, p1 = j.centre + 0.06 * a;
          svg.Line(X(p0), Y(p0), X(p1), Y(p1), std::string("axis ") + cls, {{"data-joint", j.name}});
        }
    }
    for (const auto& [name, p] : fit.markers)
      if (name.find('@') == std::string::npos)
        svg.Circle(X(p), Y(p), outliers.count(name) ? 3.2 : 1.6,
                   outliers.count(name) ? "marker outlier" : "marker", {{"data-marker", name}}, name);
    // The sd ellipse: the centre's covariance (diagonal in the parent's unscaled frame, as the
    // report gives x, y, z) carried to the lab and projected on the view's plane.
    for (const JointDrawing& j : fit.joints) {
      auto it = sds.find(j.name);
      if (it == sds.end() || !it->second.sd.allFinite()) continue;
      const Eigen::Matrix3d cov = j.parent_axes * it->second.sd.cwiseAbs2().asDiagonal() *
                                  j.parent_axes.transpose();
      Eigen::Matrix<double, 2, 3> P;
      P << view.h[0], view.h[1], view.h[2], -view.v[0], -view.v[1], -view.v[2];
      const Eigen::Matrix2d c2 = P * cov * P.transpose();
      Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(c2);
      const Eigen::Vector2d ev = eig.eigenvalues().cwiseMax(0.0).cwiseSqrt();
      const Eigen::Vector2d major = eig.eigenvectors().col(1);
      const double k = scale * in.ellipse_magnification;
      svg.Ellipse(X(j.centre), Y(j.centre), std::max(0.8, k * ev[1]), std::max(0.8, k * ev[0]),
                  std::atan2(major.y(), major.x()) * 180.0 / M_PI,
                  it->second.undetermined ? "sd undetermined" : "sd", {{"data-joint", j.name}});
    }
    for (const auto& [drawing, cls] : {std::pair{&nom, "nominal"}, std::pair{&fit, "fitted"}})
      for (const JointDrawing& j : drawing->joints)
        svg.Circle(X(j.centre), Y(j.centre), std::string(cls) == "fitted" ? 2.6 : 3.6,
                   std::string("joint ") + cls, {{"data-joint", j.name}},
                   j.name + " (" + cls + ")");
    svg.EndGroup();
    svg.Text(8, 16, view.name, "lbl");
    html += "<figure>" + svg.Finish() + "<figcaption>" + view.name + "</figcaption></figure>";
  }
  html += "</div><p class=\"legend\"><span><i class=\"sw\" style=\"background:var(--fit)\"></i>fitted "
          "segments and joint centres</span><span><i class=\"sw\" style=\"background:var(--nom)\"></i>"
          "nominal model (dashed, open circles)</span><span><i class=\"sw\" style=\"background:#e07b00\">"
          "</i>fitted joint axes (nominal: dashed)</span><span>ellipses: 1 sd of each joint centre, ×" +
          Fixed(in.ellipse_magnification, 0) +
          "</span><span><i class=\"sw\" style=\"background:var(--bad)\"></i>outlying markers</span></p>";
  return html;
}

// ---- plots -------------------------------------------------------------------------------------

// A "nice" upper bound for an axis: 1, 2 or 5 times a power of ten.
double NiceCeil(double v) {
  if (!(v > 0)) return 1;
  const double p = std::pow(10.0, std::floor(std::log10(v)));
  for (double m : {1.0, 2.0, 5.0, 10.0})
    if (m * p >= v) return m * p;
  return 10 * p;
}

std::string RmsStripsHtml(const json& report, const std::vector<TrialBand>& bands) {
  const json trials = report.value("per_trial", json::array());
  double top = 0;
  for (const auto& t : trials)
    for (const auto& v : t.value("per_frame_rms_mm", json::array()))
      if (v.is_number()) top = std::max(top, v.get<double>());
  top = NiceCeil(top);
  const double overall = Number(report, "marker_rms_mm");
  std::string html;
  for (const auto& t : trials) {
    const json frames = t.value("per_frame_rms_mm", json::array());
    constexpr double kW = 1000, kH = 92, kL = 46, kR = 10, kT = 18, kB = 18;
    SvgWriter svg(kW, kH, "strip", "marker RMS per frame of " + t.value("name", std::string()));
    svg.Rect(kL, kT, kW - kL - kR, kH - kT - kB, "band");
    const int n = static_cast<int>(frames.size());
    const double rate = Number(t, "rate_hz", 0);
    auto X = [&](double f) { return kL + (kW - kL - kR) * (n > 1 ? f / (n - 1) : 0.5); };
    auto Y = [&](double mm) { return kT + (kH - kT - kB) * (1 - mm / top); };
    for (double q : {0.5, 1.0}) {
      svg.Line(kL, Y(q * top), kW - kR, Y(q * top), "tick");
      svg.Text(kL - 4, Y(q * top) + 4, Fixed(q * top, top < 2 ? 2 : 1), "lbl small", "end");
    }
    svg.Text(kL - 4, Y(0) + 4, "0", "lbl small", "end");
    const std::string name = t.value("name", std::string("trial"));
    int shade = 0;
    for (const TrialBand& b : bands) {
      if (b.trial != name) continue;
      const double x0 = X(std::clamp(b.first_frame, 0, std::max(0, n - 1))),
                   x1 = X(std::clamp(b.last_frame, 0, std::max(0, n - 1)));
      svg.Rect(x0, kT, std::max(0.0, x1 - x0), kH - kT - kB, shade++ % 2 ? "phase alt" : "phase",
               {{"data-band", b.label}}, b.label + ": frames " + std::to_string(b.first_frame) + "–" +
                                             std::to_string(b.last_frame));
      svg.Text(x0 + 3, kH - kB - 4, b.label, "lbl small");  // low: the curve runs high
    }
    if (std::isfinite(overall)) svg.Line(kL, Y(overall), kW - kR, Y(overall), "mean");
    std::vector<std::pair<double, double>> pts;
    for (int f = 0; f < n; ++f)
      pts.emplace_back(X(f), frames[f].is_number() ? Y(frames[f].get<double>()) : kNaN);
    svg.Polyline(pts, "curve");
    svg.Text(kL + 4, 13, name + " — " + std::to_string(n) + " frames" +
                             (rate > 0 ? ", " + Fixed(n / rate, 1) + " s" : "") + ", RMS " +
                             Fixed(Number(t, "marker_rms_mm"), 2) + " mm",
             "lbl");
    svg.Text(kW - kR, kH - 4, rate > 0 ? Fixed((n - 1) / rate, 1) + " s" : std::to_string(n - 1), "lbl small", "end");
    svg.Text(kL, kH - 4, "0", "lbl small");
    html += svg.Finish();
  }
  return html + "<p class=\"legend\"><span>marker RMS per frame (mm); dashed red: the fit's overall RMS " +
         Fixed(overall, 2) + " mm; one strip per trial (each trial is one movement of the protocol); "
                            "shaded bands: the movement's phases (the protocol's windows, e.g. left "
                            "side then right), as fractions of the trial</span></p>";
}

std::string MarkerBarsHtml(const json& report, const std::set<std::string>& outliers) {
  std::vector<std::pair<std::string, double>> bars;
  const json per_marker = report.value("per_marker_rms_mm", json::object());
  for (const auto& [name, v] : per_marker.items())
    if (v.is_number() && name.find('@') == std::string::npos) bars.emplace_back(name, v.get<double>());
  if (bars.empty()) return "<p>No marker residuals in the report.</p>";
  std::sort(bars.begin(), bars.end(), [](const auto& a, const auto& b) { return a.second > b.second; });
  double top = 0;
  for (const auto& [n, v] : bars) top = std::max(top, v);
  top = NiceCeil(top);
  constexpr double kRow = 15, kL = 110, kR = 60, kW = 560;
  const double h = 22 + kRow * bars.size();
  SvgWriter svg(kW, h, "bars", "per-marker residual RMS");
  auto X = [&](double mm) { return kL + (kW - kL - kR) * mm / top; };
  for (double q : {0.0, 0.5, 1.0}) {
    svg.Line(X(q * top), 14, X(q * top), h - 4, "tick");
    svg.Text(X(q * top), 11, Fixed(q * top, top < 2 ? 2 : 1) + (q == 1.0 ? " mm" : ""), "lbl small", "middle");
  }
  const double median = Number(report, "median_marker_rms_mm");
  if (std::isfinite(median)) svg.Line(X(median), 14, X(median), h - 4, "mean");
  for (size_t i = 0; i < bars.size(); ++i) {
    const auto& [name, v] = bars[i];
    const bool bad = outliers.count(name) > 0;
    const double y = 18 + kRow * i;
    svg.Text(kL - 6, y + 10, name, bad ? "lbl bad" : "lbl", "end");
    svg.Rect(kL, y + 2, X(v) - kL, kRow - 4, bad ? "bar outlier" : "bar", {{"data-marker", name}},
             name + ": " + Fixed(v, 2) + " mm");
    svg.Text(X(v) + 4, y + 10, Fixed(v, 2) + (bad ? "  outlier" : ""), bad ? "lbl bad" : "lbl small");
  }
  return svg.Finish() + "<p class=\"legend\"><span>RMS residual per marker over all trials (mm), "
                        "largest first; dashed red: the median marker's " + Fixed(median, 2) +
         " mm; red bars: outlying markers</span></p>";
}

// Cost per iteration on a log axis (the initial cost as iteration 0).
std::string LogPlot(const std::vector<double>& values, const std::string& title,
                    const std::string& unit, const std::string& css) {
  constexpr double kW = 470, kH = 220, kL = 62, kR = 12, kT = 22, kB = 30;
  SvgWriter svg(kW, kH, "convergence", title);
  double lo = 1e300, hi = 0;
  for (double v : values)
    if (v > 0 && std::isfinite(v)) lo = std::min(lo, v), hi = std::max(hi, v);
  if (!(hi > 0)) return "";
  const double dlo = std::floor(std::log10(lo)), dhi = std::max(dlo + 1, std::ceil(std::log10(hi)));
  const int n = static_cast<int>(values.size());
  auto X = [&](double i) { return kL + (kW - kL - kR) * (n > 1 ? i / (n - 1) : 0.5); };
  auto Y = [&](double v) { return kT + (kH - kT - kB) * (dhi - std::log10(v)) / (dhi - dlo); };
  for (double d = dlo; d <= dhi; d += 1) {
    svg.Line(kL, Y(std::pow(10, d)), kW - kR, Y(std::pow(10, d)), "tick");
    svg.Text(kL - 4, Y(std::pow(10, d)) + 4, "1e" + SvgNumber(d, 0), "lbl small", "end");
  }
  svg.Line(kL, kH - kB, kW - kR, kH - kB, "axisline");
  std::vector<std::pair<double, double>> pts;
  for (int i = 0; i < n; ++i) pts.emplace_back(X(i), values[i] > 0 ? Y(values[i]) : kNaN);
  svg.Polyline(pts, "curve " + css);
  for (int i = 0; i < n; ++i)
    if (values[i] > 0) svg.Circle(X(i), Y(values[i]), 2, "dot", {}, "iteration " + std::to_string(i) + ": " + Fixed(values[i], 4));
  svg.Text(kL, 14, title + " (" + unit + ", log scale)", "lbl");
  svg.Text((kL + kW - kR) / 2, kH - 6, "iteration", "lbl small", "middle");
  svg.Text(kL, kH - kB + 12, "0", "lbl small", "middle");
  svg.Text(kW - kR, kH - kB + 12, std::to_string(std::max(0, n - 1)), "lbl small", "middle");
  return svg.Finish();
}

std::string ConvergenceHtml(const json& report) {
  const json history = report.value("iteration_history", json::array());
  std::vector<double> cost = {Number(report, "initial_cost")};
  for (const auto& it : history) cost.push_back(Number(it, "cost"));
  // The marker RMS the solver measured after each iteration (mm, the priors' rows left out),
  // from the fit's start (iteration 0). A report stored before the solver measured it has none:
  // then the residual RMS in sigma units, sqrt(2 cost / residuals), priors included, under its
  // own name.
  std::vector<double> rms = {Number(report, "initial_marker_rms_mm")};
  bool measured = !history.empty();
  for (const auto& it : history) {
    rms.push_back(Number(it, "marker_rms_mm"));
    measured &= std::isfinite(rms.back());
  }
  std::string rms_plot;
  if (measured) {
    rms_plot = LogPlot(rms, "marker RMS", "mm", "alt");
  } else {
    const double residuals = Number(report, "residuals", 0);
    rms.clear();
    for (double c : cost) rms.push_back(residuals > 0 ? std::sqrt(2 * c / residuals) : kNaN);
    rms_plot = LogPlot(rms, "residual RMS √(2 cost / residuals)", "σ", "alt");
  }
  std::string html = "<div class=\"two\">" + LogPlot(cost, "cost", "1/2 Σ r²", "") + rms_plot + "</div>";
  const bool converged = report.value("converged", false);
  html += std::string("<p class=\"") + (converged ? "good" : "alert") + "\">Termination: <b>" +
          Esc(report.value("termination", std::string("?"))) + "</b> after " +
          std::to_string(report.value("iterations", 0)) + " iterations — " +
          Esc(report.value("termination_message", std::string())) + "</p>";
  // A static trial is fitted as its mean posture: the solver's figure (the plot's end) is then
  // below the headline's, which is over the frames as measured.
  const double fitted = Number(report, "fitted_marker_rms_mm");
  const double headline = Number(report, "marker_rms_mm");
  if (measured && std::isfinite(fitted) && std::isfinite(headline) && std::abs(fitted - headline) > 0.005)
    html += "<p class=\"note\">The plot ends at " + Fixed(fitted, 2) +
            " mm, over the frames as fitted: each static trial as its mean posture. Over its frames as " +
            "measured the marker RMS is " + Fixed(headline, 2) + " mm.</p>";
  const json coarse = report.value("coarse", json::object());
  if (coarse.value("used", false))
    html += "<p class=\"note\">Coarse-to-fine start: " + std::to_string(coarse.value("iterations", 0)) +
            " iterations on " + std::to_string(coarse.value("frames", 0)) +
            " frames before the full problem (not plotted).</p>";
  return html;
}

// One joint's checks: a line per trial that excites it, or why there is no reference.
std::string FunctionalCell(const json& joint) {
  if (!joint.is_object()) return "–";
  std::string html, reasons;
  bool estimated = false;
  for (const auto& t : joint.value("trials", json::array())) {
    const std::string trial = t.value("trial", std::string());
    estimated |= t.value("estimated", false);
    if (!t.value("excited", false)) {
      reasons += (reasons.empty() ? "" : "; ") + trial + ": " + t.value("note", std::string());
      continue;
    }
    const bool far = t.value("far", false);
    html += std::string(html.empty() ? "" : "<br>") + "<span class=\"" + (far ? "bad" : "fd") + "\">";
    if (joint.value("axis_joint", false))
      html += Fixed(Number(t, "axis_angle_deg"), 1) + "° axis</span>, centre " +
              Fixed(Number(t, "axis_line_distance_mm"), 1) + " mm off it, on " + Esc(trial) +
              " <small>(spread " + Fixed(Number(t, "axis_spread_deg"), 1) + "°, SARA sd " +
              Fixed(Number(t, "functional_axis_std_deg"), 2) + "°)</small>";
    else
      html += Fixed(Number(t, "centre_distance_mm"), 1) + " mm</span> on " + Esc(trial) + " <small>(spread " +
              Fixed(Number(t, "centre_spread_mm"), 1) + " mm, SCoRE sd " + Fixed(Number(t, "functional_std_mm"), 2) +
              " mm)</small>";
  }
  // What the reference itself is worth: the two most precise trials' estimates apart.
  const bool axis = joint.value("axis_joint", false);
  const double between = Number(joint, axis ? "functional_between_trials_deg" : "functional_between_trials_mm");
  if (!html.empty() && std::isfinite(between))
    html += "<br><small>the functional " + std::string(axis ? "axes" : "centres") + " on " +
            Esc(joint.value("best_trial", std::string())) + " and " + Esc(joint.value("second_trial", std::string())) +
            " are " + Fixed(between, 1) + (axis ? "°" : " mm") + " apart</small>";
  // A hip's third reference: the regression of the pelvis markers (solver/fit_trust.h).
  std::string regression;
  for (const auto& r : joint.value("regression", json::array()))
    regression += "<br><span class=\"" + std::string(r.value("far", false) ? "bad" : "fd") + "\">" +
                  Fixed(Number(r, "centre_from_regression_mm"), 1) + " mm</span> from " +
                  Esc(r.value("method", std::string())) + "'s regression on " + Esc(r.value("trial", std::string())) +
                  " <small>(pelvis width " + Fixed(Number(r, "pelvis_width_mm"), 0) + " mm; the generic model's " +
                  Fixed(Number(r, "generic_from_regression_mm"), 1) + " mm)</small>";
  // Whether the data tell the fitted centre from the functional one (fit_trust.h, profile).
  for (const auto& p : joint.value("profile", json::array()))
    if (!p.value("note", std::string()).empty())
      regression += "<br><small>not held at its functional estimate: " + Esc(p.value("note", std::string())) +
                    "</small>";
    else
      regression += "<br><small>held at its functional " +
                  std::string(joint.value("axis_joint", false) ? "axis" : "centre") + " on " +
                  Esc(p.value("trial", std::string())) +
                  ": chi-square " + (Number(p, "delta_chi2") >= 0 ? "+" : "") + Fixed(Number(p, "delta_chi2"), 1) +
                  ", " +
                  (p.value("told_apart", false)         ? "the data side with the fit"
                   : p.value("held_fits_better", false) ? "<span class=\"bad\">the functional estimate fits better: the "
                                                          "fit ended in a worse minimum</span>"
                                                        : "<span class=\"bad\">the data cannot tell the two apart</span>") +
                  (p.value("released", false)
                       ? "; released from there, chi-square " +
                             std::string(Number(p, "released_delta_chi2") >= 0 ? "+" : "") +
                             Fixed(Number(p, "released_delta_chi2"), 1) +
                             (p.value("adopted", false) ? ": <b>adopted</b> (the fit is that minimum)" : ": not adopted")
                       : std::string()) +
                  "</small>";
  if (!html.empty()) return html + regression;
  return std::string("<span class=\"notexcited\" title=\"") + Esc(reasons) + "\">" +
         (estimated ? "not excited by any trial" : "no reference: fewer than 3 markers on a segment") + "</span>" +
         regression;
}

std::string JointTableHtml(const FitReportPage& in) {
  const auto sds = CentreSds(in.report);
  const ModelDrawing fit = DrawModel(in.fitted), nom = DrawModel(in.initial);
  const json per_marker = in.report.value("per_marker_rms_mm", json::object());
  bool any_functional = false;
  for (const auto& [name, v] : per_marker.items()) any_functional |= name.find("@functional") != std::string::npos;
  std::string html =
      "<table class=\"joints\"><tr><th>joint</th><th>type</th><th>fitted centre in parent (mm)</th>"
      "<th>generic centre (mm)</th><th>fitted − generic (mm)</th><th>sd (mm)</th>";
  // The joint checks (solver/fit_trust.h) when the report has them.
  std::map<std::string, json> checks;
  for (const auto& c : in.report.value("joint_checks", json::array()))
    if (c.is_object()) checks[c.value("joint", std::string())] = c;
  if (!checks.empty()) html += "<th>fitted − functional estimate (per trial that excites the joint)</th>";
  if (any_functional) html += "<th>fitted − functional (mm RMS)</th>";
  html += "<th></th></tr>";
  const Geometry gf(in.fitted), gn(in.initial);
  for (int j = 0; j < in.fitted.num_joints(); ++j) {
    const Joint& jf = in.fitted.joints()[j];
    const int jn = in.initial.FindJoint(jf.name);
    if (jn < 0) continue;
    if (jf.parent < 0) {  // the root: its "centre" is the pose's translation, not a parameter
      html += "<tr data-joint=\"" + Esc(jf.name) + "\"><td>" + Esc(jf.name) + "</td><td>" +
              ToString(jf.type) + "</td><td colspan=\"" + std::to_string(5 + any_functional + !checks.empty()) +
              "\">the root: placed by each frame's pose</td></tr>";
      continue;
    }
    const Eigen::Vector3d cf = gf.centre_scaled[j], cn = gn.centre_scaled[jn];
    auto it = sds.find(jf.name);
    const bool undetermined = it != sds.end() && it->second.undetermined;
    const bool fitted = it != sds.end() && it->second.fitted;
    const double sd = fitted ? 1000 * gf.scale[jf.parent] * it->second.sd.norm() : kNaN;
    auto mm = [](const Eigen::Vector3d& v) {
      return Fixed(1000 * v.x(), 1) + ", " + Fixed(1000 * v.y(), 1) + ", " + Fixed(1000 * v.z(), 1);
    };
    html += std::string("<tr") + (undetermined ? " class=\"undetermined\"" : "") + " data-joint=\"" +
            Esc(jf.name) + "\"><td>" + Esc(jf.name) + "</td><td>" + ToString(jf.type) + "</td><td>" +
            mm(cf) + "</td><td>" + mm(cn) + "</td><td>" + Fixed(1000 * (cf - cn).norm(), 1) +
            "</td><td>" + (fitted ? Fixed(sd, 1) : "not fitted") + "</td>";
    if (!checks.empty()) html += "<td class=\"functional\">" + FunctionalCell(checks[jf.name]) + "</td>";
    if (any_functional) {
      const std::string key = jf.name + "@functional";
      html += "<td>" + (per_marker.contains(key) ? Fixed(Number(per_marker, key.c_str()), 1) : "–") + "</td>";
    }
    html += std::string("<td>") + (undetermined ? "not determined by the data" : "") + "</td></tr>";
  }
  return html + "</table><p class=\"legend\"><span>centres in the parent segment's frame, scaled; "
                "sd: √(sd<sub>x</sub>² + sd<sub>y</sub>² + sd<sub>z</sub>²) of the centre from the "
                "fit's covariance; greyed: the data did not determine the centre (it stayed near the "
                "generic model)</span>" +
         (checks.empty() ? std::string()
                         : "<span>functional estimate: SCoRE's centre (ball and custom joints) or SARA's "
                           "axis (hinges) from the two segments' markers alone, independent of the fit; "
                           "both centres expressed in the fitted parent segment's frame in every frame of "
                           "the trial and averaged, the distance is between the averages; spread: RMS of "
                           "the per-frame functional centre (axis) about its average; red: far from the "
                           "estimate (the fit's threshold)</span>") +
         "</p>";
}

std::string ParametersHtml(const json& report) {
  const json undetermined = report.value("undetermined", json::array());
  std::string html;
  std::set<std::string> und;
  for (const auto& u : undetermined) und.insert(u.get<std::string>());
  html += "<table class=\"scales\"><tr><th>segment scale</th><th>generic</th><th>fitted</th><th>sd</th></tr>";
  for (const auto& p : report.value("parameters", json::array())) {
    if (p.value("group", "") != "scales" && p.value("group", "") != "scale") continue;
    const std::string name = p.value("name", "");
    const bool u = und.count(name) > 0 || !p.value("determined", true);
    html += std::string("<tr") + (u ? " class=\"undetermined\"" : "") + "><td>" + Esc(name) + "</td><td>" +
            Fixed(Number(p, "initial"), 3) + "</td><td>" + Fixed(Number(p, "value"), 3) + "</td><td>" +
            Fixed(Number(p, "std"), 4) + "</td></tr>";
  }
  html += "</table>";
  if (undetermined.empty())
    return html + "<p class=\"good\" id=\"all-determined\">The data determined every fitted parameter.</p>";
  html += "<div class=\"note\" id=\"undetermined\"><b>" + std::to_string(undetermined.size()) +
          " parameters not determined by these trials</b> (kept near the initial model; their posterior "
          "sd exceeds the set fraction of their prior sd):<ul>";
  std::map<std::string, json> by_name;
  for (const auto& p : report.value("parameters", json::array())) by_name[p.value("name", "")] = p;
  for (const auto& u : undetermined) {
    const std::string name = u.get<std::string>();
    const json& p = by_name[name];
    html += "<li class=\"undetermined\">" + Esc(name) +
            (p.is_object() ? ": " + Fixed(Number(p, "initial"), 4) + " → " + Fixed(Number(p, "value"), 4) +
                                 " (sd " + Fixed(Number(p, "std"), 4) + ")"
                           : "") +
            "</li>";
  }
  return html + "</ul></div>";
}

std::string CoverageHtml(const std::vector<CoverageRow>& rows) {
  if (rows.empty())
    return "<p class=\"note\">No protocol coverage was given for this fit (the daemon checks each "
           "recording against the protocol; `mocap fit` on files has none).</p>";
  double lo = 0, hi = 0;
  for (const auto& r : rows)
    for (double v : {r.required_min_deg, r.required_max_deg, r.reached_min_deg, r.reached_max_deg})
      if (std::isfinite(v)) lo = std::min(lo, v), hi = std::max(hi, v);
  lo = -NiceCeil(-lo + 1e-9), hi = NiceCeil(hi);
  constexpr double kRow = 18, kL = 250, kR = 210, kW = 1000;
  const double h = 24 + kRow * rows.size();
  SvgWriter svg(kW, h, "coverage", "protocol coverage");
  auto X = [&](double d) { return kL + (kW - kL - kR) * (d - lo) / (hi - lo); };
  for (double d : {lo, 0.0, hi}) {
    svg.Line(X(d), 14, X(d), h - 2, "tick");
    svg.Text(X(d), 11, Fixed(d, 0) + "°", "lbl small", "middle");
  }
  for (size_t i = 0; i < rows.size(); ++i) {
    const CoverageRow& r = rows[i];
    const double y = 18 + kRow * i;
    svg.Text(kL - 6, y + 11, r.movement + ": " + r.coordinate + (r.required ? "" : " (optional)"),
             r.ok ? "lbl" : "lbl bad", "end");
    svg.Rect(X(r.required_min_deg), y + 2, X(r.required_max_deg) - X(r.required_min_deg), kRow - 4, "required");
    if (std::isfinite(r.reached_min_deg) && std::isfinite(r.reached_max_deg))
      svg.Rect(X(r.reached_min_deg), y + 6, X(r.reached_max_deg) - X(r.reached_min_deg), kRow - 12,
               r.ok ? "reached" : "reached fail");
    svg.Text(kW - kR + 6, y + 11,
             "[" + Fixed(r.reached_min_deg, 0) + ", " + Fixed(r.reached_max_deg, 0) + "] of [" +
                 Fixed(r.required_min_deg, 0) + ", " + Fixed(r.required_max_deg, 0) + "]° " +
                 (r.ok ? "ok" : "NOT reached"),
             r.ok ? "lbl" : "lbl bad");
  }
  return svg.Finish() + "<p class=\"legend\"><span>grey: range required by the protocol; blue: range "
                        "reached (red: not enough)</span></p>";
}

std::string InputsHtml(const FitReportPage& in) {
  const json& r = in.report;
  std::string html = "<div class=\"two\"><div><table><tr><th>model file</th><td>" + Esc(in.model_file) +
                     "</td></tr><tr><th>model</th><td>" + Esc(in.initial.name()) + " (" +
                     std::to_string(in.initial.num_joints()) + " joints, " +
                     std::to_string(in.initial.num_markers()) + " markers)</td></tr>";
  for (const auto& [k, label] : std::vector<std::pair<const char*, const char*>>{
           {"frames", "frames"}, {"markers", "markers with data"}, {"marker_samples", "marker samples"},
           {"unknowns", "unknowns"}, {"residuals", "residuals"}})
    html += std::string("<tr><th>") + label + "</th><td>" + (r.contains(k) ? r[k].dump() : "–") + "</td></tr>";
  html += "<tr><th>wall time</th><td>" + Fixed(Number(r, "wall_seconds"), 1) + " s</td></tr>";
  html += "<tr><th>software</th><td>" + Esc(in.software_version) + "</td></tr><tr><th>date</th><td>" +
          Esc(in.date) + "</td></tr></table></div><div><table><tr><th>option</th><th>value</th></tr>";
  for (const auto& [k, v] : in.options.items())
    html += "<tr><td>" + Esc(k) + "</td><td>" + Esc(v.is_string() ? v.get<std::string>() : v.dump()) + "</td></tr>";
  html += "</table></div></div><table><tr><th>trial</th><th>file</th><th>frames</th><th>rate (Hz)</th>"
          "<th>marker RMS (mm)</th></tr>";
  for (const auto& t : r.value("per_trial", json::array()))
    html += "<tr><td>" + Esc(t.value("name", std::string())) + "</td><td>" + Esc(t.value("file", std::string())) +
            "</td><td>" + std::to_string(t.value("frames", 0)) + "</td><td>" + Fixed(Number(t, "rate_hz"), 1) +
            "</td><td>" + Fixed(Number(t, "marker_rms_mm"), 2) + "</td></tr>";
  html += "</table>";
  for (const auto& [key, label] : std::vector<std::pair<const char*, const char*>>{
           {"unmatched_trial_markers", "in the trials but not in the model (ignored)"},
           {"unobserved_model_markers", "in the model but in no trial (not fitted)"}}) {
    const json list = r.value(key, json::array());
    if (list.empty()) continue;
    std::string names;
    for (const auto& n : list) names += (names.empty() ? "" : ", ") + Esc(n.get<std::string>());
    html += "<p class=\"note\">Markers " + std::string(label) + ": " + names + "</p>";
  }
  return html;
}

std::string Card(const std::string& key, const std::string& value, const std::string& id = "") {
  return "<div class=\"card\"" + (id.empty() ? "" : " id=\"" + id + "\"") + "><div class=\"k\">" + key +
         "</div><div class=\"v\">" + value + "</div></div>";
}

}  // namespace

const std::vector<OrthographicView>& SkeletonViews() {
  static const std::vector<OrthographicView> views = {
      {"front", {0, 1, 0}, {0, 0, 1}},   // from in front: the subject's left on the right
      {"side", {1, 0, 0}, {0, 0, 1}},    // from the subject's right: anterior to the right
      {"top", {0, 1, 0}, {-1, 0, 0}},    // from above, aligned with the front view: anterior down
  };
  return views;
}

bool FitReportPage::IsValid(std::string* error) const {
  if (!report.is_object()) return *error = "report: not a JSON object", false;
  for (const char* key : {"marker_rms_mm", "iterations", "termination", "per_trial", "parameters",
                          "per_marker_rms_mm", "residuals", "initial_cost"})
    if (!report.contains(key))
      return *error = std::string("report: no '") + key + "' (not a fit report of solver/fit_report_json.h?)", false;
  if (fitted.num_joints() == 0) return *error = "fitted model: empty", false;
  for (const Joint& j : fitted.joints())
    if (initial.FindJoint(j.name) < 0)
      return *error = "initial model '" + initial.name() + "' has no joint '" + j.name +
                      "' of the fitted model: not the model the fit started from",
             false;
  if (!(ellipse_magnification > 0))
    return *error = "ellipse_magnification: must be > 0, got " + Fixed(ellipse_magnification, 3), false;
  return true;
}

Status WriteFitReportHtml(const FitReportPage& in, std::string* html) {
  std::string error;
  if (!in.IsValid(&error)) return Status::Error("fit report page: " + error);
  const json& r = in.report;
  std::set<std::string> outliers;
  std::string outlier_text;
  const double median = Number(r, "median_marker_rms_mm");
  const json outlier_markers = r.value("outlier_markers", json::object());
  for (const auto& [name, v] : outlier_markers.items()) {
    outliers.insert(name);
    outlier_text += std::string(outlier_text.empty() ? "" : "; ") + "<b>" + Esc(name) + "</b> " +
                    Fixed(v.get<double>(), 1) + " mm (" + Fixed(v.get<double>() / std::max(1e-9, median), 1) +
                    "× the median)";
  }
  const bool converged = r.value("converged", false);
  const size_t n_undetermined = r.value("undetermined", json::array()).size();

  std::string out = "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
                    "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
                    "<title>" + Esc(in.title) + "</title><style>" + kStyle + "</style></head><body>";
  out += "<h1>" + Esc(in.title) + "</h1><p class=\"sub\">" + Esc(in.initial.name()) + " fitted to " +
         std::to_string(r.value("trials", 0)) + " trials, " + std::to_string(r.value("frames", 0)) +
         " frames · " + Esc(in.software_version) + " · " + Esc(in.date) + "</p>";
  out += "<div class=\"cards\">" +
         Card("marker RMS", Fixed(Number(r, "marker_rms_mm"), 2) + " mm", "rms") +
         Card("before the fit", Fixed(Number(r, "initial_marker_rms_mm"), 2) + " mm") +
         Card("iterations", std::to_string(r.value("iterations", 0)), "iterations") +
         Card("termination", std::string(converged ? "<span>" : "<span class=\"bad\">") +
                                 Esc(r.value("termination", std::string())) + "</span>") +
         Card("outlying markers", std::to_string(outliers.size())) +
         Card("undetermined parameters", std::to_string(n_undetermined)) + "</div>";
  if (!converged)
    out += "<div class=\"alert\" id=\"not-converged\"><b>The fit did not converge</b>: it stopped on <b>" +
           Esc(r.value("termination", std::string())) + "</b> (" + Esc(r.value("termination_message", std::string())) +
           ") after " + std::to_string(r.value("iterations", 0)) +
           " iterations. The model is the last iterate: check the convergence plot before using it.</div>";
  if (!outliers.empty()) {
    // Each one's likeliest cause, where the fit diagnosed it (solver/marker_diagnosis.h).
    std::string why;
    for (const auto& d : r.value("marker_diagnoses", json::array()))
      if (d.value("text", std::string()).size())
        why += "<li data-marker=\"" + Esc(d.value("marker", std::string())) + "\" data-kind=\"" +
               Esc(d.value("kind", std::string())) + "\">" + Esc(d.value("text", std::string())) + "</li>";
    out += "<div class=\"alert\" id=\"outliers\"><b>Outlying markers</b> (mislabelled, slipping, or on "
           "another body than the model's?): " + outlier_text +
           (why.empty() ? "" : "<ul class=\"diagnoses\">" + why + "</ul>") + "</div>";
  }
  std::string far;
  for (const auto& joint : r.value("joint_checks", json::array()))
    for (const auto& t : joint.value("trials", json::array()))
      if (t.value("far", false))
        far += std::string(far.empty() ? "" : "; ") + "<b>" + Esc(joint.value("joint", std::string())) + "</b> " +
               (joint.value("axis_joint", false) ? Fixed(Number(t, "axis_angle_deg"), 1) + "° (axis)"
                                                 : Fixed(Number(t, "centre_distance_mm"), 1) + " mm") +
               " on " + Esc(t.value("trial", std::string()));
  if (!far.empty())
    out += "<div class=\"alert\" id=\"functional-far\"><b>Fitted joints far from their functional "
           "estimates</b> (which need no model: a wrong minimum, or a model that cannot take this "
           "subject's joint?): " + far + "</div>";
  if (n_undetermined > 0)
    out += "<div class=\"note\"><b>" + std::to_string(n_undetermined) +
           " parameters were not determined</b> by these trials; they are greyed below.</div>";

  out += "<section><h2>Skeleton: fitted against nominal</h2>" + SkeletonViewsHtml(in, outliers) + "</section>";
  out += "<section><h2>Marker RMS over time</h2>" + RmsStripsHtml(r, in.bands) + "</section>";
  out += "<section><h2>Per-marker residuals</h2>" + MarkerBarsHtml(r, outliers) + "</section>";
  out += "<section><h2>Joints</h2>" + JointTableHtml(in) + "</section>";
  out += "<section><h2>Scales and undetermined parameters</h2>" + ParametersHtml(r) + "</section>";
  out += "<section><h2>Protocol coverage</h2>" + CoverageHtml(in.coverage) + "</section>";
  out += "<section><h2>Convergence</h2>" + ConvergenceHtml(r) + "</section>";
  out += "<section><h2>Inputs</h2>" + InputsHtml(in) + "</section>";
  out += "</body></html>\n";
  *html = std::move(out);
  return Status::Ok();
}

Status AppendCoverageRows(const std::string& movement, const std::string& coverage_json,
                          std::vector<CoverageRow>* rows) {
  const json coverage = json::parse(coverage_json, nullptr, false);
  const std::string where = "coverage of '" + movement + "'";
  if (!coverage.is_object() || !coverage.contains("excitations") || !coverage["excitations"].is_array())
    return Status::Error(where + ": not an object with an 'excitations' array");
  std::vector<CoverageRow> add;
  for (const json& e : coverage["excitations"]) {
    CoverageRow row;
    row.movement = movement;
    if (!e.is_object() || !e.contains("coordinate") || !e["coordinate"].is_string())
      return Status::Error(where + ": an excitation without a 'coordinate' string");
    row.coordinate = e["coordinate"].get<std::string>();
    row.required_min_deg = Number(e, "min_deg");
    row.required_max_deg = Number(e, "max_deg");
    if (!std::isfinite(row.required_min_deg) || !std::isfinite(row.required_max_deg))
      return Status::Error(where + ", " + row.coordinate + ": 'min_deg' and 'max_deg' must be numbers");
    row.reached_min_deg = Number(e, "reached_min_deg");
    row.reached_max_deg = Number(e, "reached_max_deg");
    row.required = e.value("required", true);
    row.ok = e.value("ok", false);
    add.push_back(row);
  }
  rows->insert(rows->end(), add.begin(), add.end());
  return Status::Ok();
}

Status FitReportPageFromJson(const std::string& report_json, const std::string& initial_model_json,
                             const std::string& fitted_model_json, FitReportPage* page) {
  FitReportPage p;
  p.report = json::parse(report_json, nullptr, false);
  if (p.report.is_discarded()) return Status::Error("fit report page: the report is not valid JSON");
  MOCAP_RETURN_IF_ERROR(ParseModelJson(initial_model_json, "initial model", &p.initial));
  MOCAP_RETURN_IF_ERROR(ParseModelJson(fitted_model_json, "fitted model", &p.fitted));
  *page = std::move(p);
  return Status::Ok();
}

}  // namespace mocap::report
