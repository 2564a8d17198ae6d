#pragma once
// The console's pages, styles and scripts (gateway/console/web/), embedded in the program at
// build time (embed_web.cmake), so the console works the same from the build tree, the package
// and the container (docs/DECISIONS.md "Browser console"). Chart.js is the Debian package's,
// read from /usr/share/javascript at start.
#include <span>
#include <string_view>

namespace sms::gateway::console {

struct WebAsset {
  std::string_view name;  // "overview.html", "console.js"
  std::string_view content_type;
  std::string_view bytes;
};

std::span<const WebAsset> web_assets();
const WebAsset* find_web_asset(std::string_view name);

// Where libjs-chart.js installs the UMD build the pages load as /vendor/chart.js.
inline constexpr std::string_view kChartJsPath = "/usr/share/javascript/chart.js/chart.min.js";

}  // namespace sms::gateway::console
