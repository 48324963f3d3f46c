// dtraced::cli JSON config files for CLI11.
//
// `--config FILE` takes a JSON object whose keys are the long flag names in snake_case
// ("state_dir" for --state-dir) and whose values are strings, numbers, booleans or arrays of
// those. CLI11 applies them only to options not given on the command line, so flags win.
// The file is read by jsonio's strict reader, as scenes and request bodies are: a syntax error
// names its line and column, duplicate keys are errors, and unknown keys, nested objects and
// nulls are errors that name the file and the key (an unknown key with a did-you-mean).
// Stateless apart from its construction arguments: thread-safe.
#pragma once

#include <cstddef>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include <CLI/CLI.hpp>

#include "util/result.h"

namespace dtraced::cli {

// Config files are small; anything larger is a mistake.
inline constexpr std::size_t kMaxConfigBytes = 1 << 20;

// The items of config text `text` (labelled `file_name` in errors), for the long option names
// (without dashes) in `known`; or every problem found.
util::Result<std::vector<CLI::ConfigItem>, util::Errors> read_config_items(std::string_view text,
                                                                           const std::string& file_name,
                                                                           const std::set<std::string>& known);

// Adds --config to `app`, for the options `app` has at this point (but --help, --version and
// --config itself). `file_name` labels errors: CLI11 hands the reader only a stream.
void add_config_option(CLI::App& app, std::string file_name);

class JsonConfig : public CLI::Config {
 public:
  // `known` holds the long option names (without dashes) the file may set.
  JsonConfig(std::string file_name, std::set<std::string> known);

  std::string to_config(const CLI::App*, bool, bool, std::string) const override;
  // read_config_items, its errors thrown as one CLI::ConfigError (a line each).
  std::vector<CLI::ConfigItem> from_config(std::istream& input) const override;

 private:
  std::string file_name_;
  std::set<std::string> known_;
};

}  // namespace dtraced::cli
