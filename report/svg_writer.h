// A small SVG writer for the fit report (report/fit_report_html.h): lines, circles, ellipses,
// polylines, rectangles and text, written as inline SVG elements into a string.
//
// Why our own: the report must be ONE self-contained file (inline SVG, no script, nothing
// fetched), and there is no C++ plotting library in Debian worth the dependency for a handful of
// strips, bars and three orthographic views — gnuplot/matplotlib would mean another process or
// language, and their output embeds fonts or scripts we would then have to strip. What the
// report draws is simple geometry; styling is left to the page's CSS through class names, so
// the same drawing prints (the @media print rules) and reads on screen.
#pragma once

#include <string>
#include <utility>
#include <vector>

namespace mocap::report {

// Extra attributes of an element, e.g. {"data-joint", "knee_r"} (values are escaped).
using SvgAttributes = std::vector<std::pair<std::string, std::string>>;

// Text for HTML/SVG content and attribute values: & < > " ' escaped.
std::string EscapeXml(const std::string& text);
// A number as SVG wants it: fixed, up to `decimals` decimals, no locale.
std::string SvgNumber(double value, int decimals = 2);

class SvgWriter {
 public:
  // The drawing's size in user units (= CSS pixels on screen); it scales with the page width
  // through its viewBox.
  SvgWriter(double width, double height, const std::string& css_class = "",
            const std::string& aria_label = "");

  void Line(double x1, double y1, double x2, double y2, const std::string& css_class,
            const SvgAttributes& attributes = {});
  void Circle(double cx, double cy, double r, const std::string& css_class,
              const SvgAttributes& attributes = {}, const std::string& tooltip = "");
  // An ellipse with semi-axes rx, ry, its rx axis turned by angle_deg (clockwise on screen).
  void Ellipse(double cx, double cy, double rx, double ry, double angle_deg,
               const std::string& css_class, const SvgAttributes& attributes = {});
  void Rect(double x, double y, double width, double height, const std::string& css_class,
            const SvgAttributes& attributes = {}, const std::string& tooltip = "");
  // Joins consecutive points; a NaN coordinate breaks the line (a gap in the data).
  void Polyline(const std::vector<std::pair<double, double>>& points, const std::string& css_class);
  // anchor: "start", "middle" or "end".
  void Text(double x, double y, const std::string& text, const std::string& css_class,
            const std::string& anchor = "start");
  void BeginGroup(const std::string& css_class, const SvgAttributes& attributes = {});
  void EndGroup();

  std::string Finish();  // the <svg> element; the writer is then empty

 private:
  static std::string Attributes(const SvgAttributes& attributes);
  std::string body_;
  std::string open_;
  int open_groups_ = 0;
};

}  // namespace mocap::report
