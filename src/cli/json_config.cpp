#include "cli/json_config.h"

#include <algorithm>
#include <memory>
#include <optional>
#include <utility>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>
#include <boost/json/value.hpp>
#include <fmt/format.h>

#include "jsonio/reader.h"

namespace dtraced::cli {

namespace {

namespace json = boost::json;

// A top-level object of scalars and arrays of scalars.
constexpr std::size_t kMaxConfigDepth = 4;
constexpr std::size_t kMaxConfigErrors = 20;

std::optional<std::string> scalar_text(jsonio::Reader& r, const json::value& v, const jsonio::Path& at) {
  switch (v.kind()) {
    case json::kind::string:
      return std::string(v.get_string());
    case json::kind::bool_:
      return v.get_bool() ? "true" : "false";
    case json::kind::int64:
      return std::to_string(v.get_int64());
    case json::kind::uint64:
      return std::to_string(v.get_uint64());
    case json::kind::double_:
      return fmt::format("{}", v.get_double());
    default:
      r.error(at, fmt::format("expected a string, number, boolean or an array of those, got {}", jsonio::kind_name(v)));
      return std::nullopt;
  }
}

}  // namespace

util::Result<std::vector<CLI::ConfigItem>, util::Errors> read_config_items(std::string_view text,
                                                                           const std::string& file_name,
                                                                           const std::set<std::string>& known) {
  jsonio::Reader r(file_name, kMaxConfigErrors);
  const std::optional<json::value> doc = r.parse(text, "config file", kMaxConfigBytes, kMaxConfigDepth);
  const jsonio::Path root;
  const json::object* o = doc ? r.object(*doc, root) : nullptr;
  if (o == nullptr) return r.take_errors();

  // The file spells option names in snake_case ("state_dir" for --state-dir); as in CLI11's own
  // formats, "state-dir" is read the same.
  std::vector<std::string> snake_names;
  for (std::string name : known) {
    std::replace(name.begin(), name.end(), '-', '_');
    snake_names.push_back(std::move(name));
  }
  const std::vector<std::string_view> snake_views(snake_names.begin(), snake_names.end());

  std::vector<CLI::ConfigItem> items;
  for (const auto& [key, value] : *o) {
    const jsonio::Path at = root.key(key);
    CLI::ConfigItem item;
    item.name = std::string(key);
    std::replace(item.name.begin(), item.name.end(), '_', '-');
    if (!known.contains(item.name)) {
      r.error(at, jsonio::unknown_key_message(key, snake_views));
      continue;
    }
    if (const json::array* a = value.if_array()) {
      for (std::size_t i = 0; i < a->size(); ++i) {
        if (auto s = scalar_text(r, (*a)[i], at.index(i))) item.inputs.push_back(std::move(*s));
      }
    } else if (auto s = scalar_text(r, value, at)) {
      item.inputs.push_back(std::move(*s));
    }
    items.push_back(std::move(item));
  }
  if (r.failed()) return r.take_errors();
  return items;
}

void add_config_option(CLI::App& app, std::string file_name) {
  app.set_config("--config", "", "JSON file of role options (keys: long flag names, e.g. state_dir)");
  std::set<std::string> known;
  for (const CLI::Option* opt : app.get_options()) {
    for (const std::string& name : opt->get_lnames()) {
      if (name != "help" && name != "version" && name != "config") known.insert(name);
    }
  }
  app.config_formatter(std::make_shared<JsonConfig>(std::move(file_name), std::move(known)));
}

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
      throw CLI::ConfigError(
          fmt::format("{}: config file is larger than the limit of {} bytes", file_name_, kMaxConfigBytes));
    }
  }
  auto items = read_config_items(text, file_name_, known_);
  if (!items) throw CLI::ConfigError(util::to_string(items.error()));
  return std::move(items).value();
}

}  // namespace dtraced::cli
