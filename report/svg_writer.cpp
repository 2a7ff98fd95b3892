#include "report/svg_writer.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

namespace mocap::report {

std::string EscapeXml(const std::string& text) {
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    switch (c) {
      case '&': out += "&amp;"; break;
      case '<': out += "&lt;"; break;
      case '>': out += "&gt;"; break;
      case '"': out += "&quot;"; break;
      case '\'': out += "&#39;"; break;
      default: out += c;
    }
  }
  return out;
}

std::string SvgNumber(double value, int decimals) {
  if (!std::isfinite(value)) return "0";
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, value);
  std::string s = buf;
  if (s.find('.') != std::string::npos) {
    while (s.back() == '0') s.pop_back();
    if (s.back() == '.') s.pop_back();
  }
  return s == "-0" ? "0" : s;
}

SvgWriter::SvgWriter(double width, double height, const std::string& css_class,
                     const std::string& aria_label) {
  open_ = "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"0 0 " + SvgNumber(width) + " " +
          SvgNumber(height) + "\" width=\"" + SvgNumber(width) + "\" height=\"" +
          SvgNumber(height) + "\"";
  if (!css_class.empty()) open_ += " class=\"" + EscapeXml(css_class) + "\"";
  if (!aria_label.empty()) open_ += " role=\"img\" aria-label=\"" + EscapeXml(aria_label) + "\"";
  open_ += ">";
}

std::string SvgWriter::Attributes(const SvgAttributes& attributes) {
  std::string out;
  for (const auto& [k, v] : attributes) out += " " + k + "=\"" + EscapeXml(v) + "\"";
  return out;
}

void SvgWriter::Line(double x1, double y1, double x2, double y2, const std::string& css_class,
                     const SvgAttributes& attributes) {
  body_ += "<line x1=\"" + SvgNumber(x1) + "\" y1=\"" + SvgNumber(y1) + "\" x2=\"" +
           SvgNumber(x2) + "\" y2=\"" + SvgNumber(y2) + "\" class=\"" + css_class + "\"" +
           Attributes(attributes) + "/>";
}

void SvgWriter::Circle(double cx, double cy, double r, const std::string& css_class,
                       const SvgAttributes& attributes, const std::string& tooltip) {
  body_ += "<circle cx=\"" + SvgNumber(cx, 3) + "\" cy=\"" + SvgNumber(cy, 3) + "\" r=\"" +
           SvgNumber(r) + "\" class=\"" + css_class + "\"" + Attributes(attributes);
  body_ += tooltip.empty() ? "/>" : "><title>" + EscapeXml(tooltip) + "</title></circle>";
}

void SvgWriter::Ellipse(double cx, double cy, double rx, double ry, double angle_deg,
                        const std::string& css_class, const SvgAttributes& attributes) {
  body_ += "<ellipse cx=\"" + SvgNumber(cx, 3) + "\" cy=\"" + SvgNumber(cy, 3) + "\" rx=\"" +
           SvgNumber(rx) + "\" ry=\"" + SvgNumber(ry) + "\" transform=\"rotate(" +
           SvgNumber(angle_deg) + " " + SvgNumber(cx, 3) + " " + SvgNumber(cy, 3) +
           ")\" class=\"" + css_class + "\"" + Attributes(attributes) + "/>";
}

void SvgWriter::Rect(double x, double y, double width, double height, const std::string& css_class,
                     const SvgAttributes& attributes, const std::string& tooltip) {
  body_ += "<rect x=\"" + SvgNumber(x) + "\" y=\"" + SvgNumber(y) + "\" width=\"" +
           SvgNumber(std::max(0.0, width)) + "\" height=\"" + SvgNumber(std::max(0.0, height)) +
           "\" class=\"" + css_class + "\"" + Attributes(attributes);
  body_ += tooltip.empty() ? "/>" : "><title>" + EscapeXml(tooltip) + "</title></rect>";
}

void SvgWriter::Polyline(const std::vector<std::pair<double, double>>& points,
                         const std::string& css_class) {
  std::string run;
  int count = 0;
  auto flush = [&] {
    if (count >= 2) body_ += "<polyline points=\"" + run + "\" class=\"" + css_class + "\"/>";
    else if (count == 1) body_ += "<polyline points=\"" + run + run + "\" class=\"" + css_class + "\"/>";
    run.clear();
    count = 0;
  };
  for (const auto& [x, y] : points) {
    if (!std::isfinite(x) || !std::isfinite(y)) {
      flush();
      continue;
    }
    run += SvgNumber(x) + "," + SvgNumber(y) + " ";
    ++count;
  }
  flush();
}

void SvgWriter::Text(double x, double y, const std::string& text, const std::string& css_class,
                     const std::string& anchor) {
  body_ += "<text x=\"" + SvgNumber(x) + "\" y=\"" + SvgNumber(y) + "\" class=\"" + css_class +
           "\" text-anchor=\"" + anchor + "\">" + EscapeXml(text) + "</text>";
}

void SvgWriter::BeginGroup(const std::string& css_class, const SvgAttributes& attributes) {
  body_ += "<g class=\"" + css_class + "\"" + Attributes(attributes) + ">";
  ++open_groups_;
}

void SvgWriter::EndGroup() {
  if (open_groups_ == 0) return;
  body_ += "</g>";
  --open_groups_;
}

std::string SvgWriter::Finish() {
  while (open_groups_ > 0) EndGroup();
  std::string out = open_ + body_ + "</svg>";
  body_.clear();
  return out;
}

}  // namespace mocap::report
