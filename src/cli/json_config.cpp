#include "cli/json_config.h"

#include <iterator>
#include <sstream>

#include <boost/json.hpp>
#include <fmt/format.h>

namespace dtraced::cli {

namespace {

std::string scalar_text(const boost::json::value& v, const std::string& where) {
  switch (v.kind()) {
    case boost::json::kind::string:
      return std::string(v.get_string());
    case boost::json::kind::bool_:
      return v.get_bool() ? "true" : "false";
    case boost::json::kind::int64:
      return std::to_string(v.get_int64());
    case boost::json::kind::uint64:
      return std::to_string(v.get_uint64());
    case boost::json::kind::double_:
      return fmt::format("{}", v.get_double());
    default:
      throw CLI::ConfigError(fmt::format("{}: expected a string, number or boolean", where));
  }
}

}  // namespace

JsonConfig::JsonConfig(std::string file_name, std::set<std::string> known)
    : file_name_(std::move(file_name)), known_(std::move(known)) {}

std::string JsonConfig::to_config(const CLI::App*, bool, bool, std::string) const {
  return {};  // writing configs back is not offered
}

std::vector<CLI::ConfigItem> JsonConfig::from_config(std::istream& input) const {
  std::string text;
  text.reserve(4096);
  char buf[4096];
  while (input.read(buf, sizeof buf) || input.gcount() > 0) {
    text.append(buf, static_cast<std::size_t>(input.gcount()));
    if (text.size() > kMaxConfigBytes) {
      throw CLI::ConfigError(fmt::format("{}: larger than {} bytes", file_name_, kMaxConfigBytes));
    }
  }
  boost::json::parse_options opts;
  opts.max_depth = 4;
  boost::system::error_code ec;
  const boost::json::value doc = boost::json::parse(text, ec, {}, opts);
  if (ec) throw CLI::ConfigError(fmt::format("{}: not valid JSON: {}", file_name_, ec.message()));
  if (!doc.is_object()) throw CLI::ConfigError(fmt::format("{}: the top level must be a JSON object", file_name_));

  std::vector<CLI::ConfigItem> items;
  for (const auto& [key, value] : doc.get_object()) {
    std::string name(key);
    const std::string where = fmt::format("{}: /{}", file_name_, name);
    for (char& c : name)
      if (c == '_') c = '-';
    if (!known_.contains(name)) {
      throw CLI::ConfigError(fmt::format("{}: unknown key (see --help for the options a config may set)", where));
    }
    CLI::ConfigItem item;
    item.name = name;
    if (value.is_array()) {
      for (const boost::json::value& e : value.get_array()) item.inputs.push_back(scalar_text(e, where));
    } else {
      item.inputs.push_back(scalar_text(value, where));
    }
    items.push_back(std::move(item));
  }
  return items;
}

}  // namespace dtraced::cli
