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

util::Result<std::vector<CLI::ConfigItem>, util::Errors> read_config_items(
    std::string_view text, const std::string& file_name, const std::set<std::string>& known,
    std::map<std::string, std::string, std::less<>>* pointers) {
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
    if (pointers != nullptr) (*pointers)[item.name] = at.str();
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
  app.config_formatter(std::make_shared<JsonConfig>(std::move(file_name), std::move(known), &app));
}

util::Error option_error(const CLI::App& app, std::string_view flag, std::string message) {
  const auto config = std::dynamic_pointer_cast<const JsonConfig>(app.get_config_formatter());
  const std::string pointer = config && flag.starts_with("--") ? config->pointer_of(flag.substr(2)) : "";
  if (pointer.empty()) return util::Error{std::move(message), std::string(flag)};
  return util::Error{std::move(message), pointer, config->file_name()};
}

std::string locate_refused_value(const CLI::App& app, const std::string& message) {
  // CLI11 words these "--flag: problem" (ValidationError) or "Could not convert: --flag = value".
  constexpr std::string_view kConvert = "Could not convert: ";
  const bool conversion = message.starts_with(kConvert);
  const std::size_t start = conversion ? kConvert.size() : 0;
  const std::size_t end = message.find(conversion ? " = " : ": ", start);
  if (end == std::string::npos || message.compare(start, 2, "--") != 0) return message;
  const std::string flag = message.substr(start, end - start);
  const util::Error located = option_error(app, flag, "");
  if (located.file.empty()) return message;
  const std::string problem = conversion ? "cannot convert " + message.substr(end + 3) : message.substr(end + 2);
  return fmt::format("{}: {}: {} (for {})", located.file, located.path, problem, flag);
}

JsonConfig::JsonConfig(std::string file_name, std::set<std::string> known, const CLI::App* app)
    : file_name_(std::move(file_name)), known_(std::move(known)), app_(app) {}

std::string JsonConfig::pointer_of(std::string_view long_name) const {
  const auto it = pointers_.find(long_name);
  return it == pointers_.end() ? "" : it->second;
}

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
  std::map<std::string, std::string, std::less<>> pointers;
  auto items = read_config_items(text, file_name_, known_, &pointers);
  if (!items) throw CLI::ConfigError(util::to_string(items.error()));
  // CLI11 reads the file after the command line and applies a value only to an option the
  // command line left empty (flags win): those are the values the file is answerable for.
  for (auto& [name, pointer] : pointers) {
    const CLI::Option* opt = app_ != nullptr ? app_->get_option_no_throw("--" + name) : nullptr;
    if (opt != nullptr && opt->empty()) pointers_[name] = std::move(pointer);
  }
  return std::move(items).value();
}

}  // namespace dtraced::cli
