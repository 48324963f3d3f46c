// dtraced::cli JSON config files for CLI11.
//
// `--config FILE` takes a JSON object whose keys are the long flag names in snake_case
// ("state_dir" for --state-dir) and whose values are strings, numbers, booleans or arrays of
// those. CLI11 applies them only to options not given on the command line, so flags win.
// The file is read by jsonio's strict reader, as scenes and request bodies are: a syntax error
// names its line and column, duplicate keys are errors, and unknown keys, nested objects and
// nulls are errors that name the file and the key (an unknown key with a did-you-mean).
// A value the file set that is then refused is reported at its key in the file; a value given
// on the command line, by its flag (option_error, locate_refused_value).
// Not thread-safe: a JsonConfig records what it read while CLI11 parses, on main's thread.
#pragma once

#include <cstddef>
#include <functional>
#include <map>
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
// (without dashes) in `known`; or every problem found. `pointers`, when given, receives each
// item's JSON Pointer ("/state_dir") by its option name ("state-dir").
util::Result<std::vector<CLI::ConfigItem>, util::Errors> read_config_items(
    std::string_view text, const std::string& file_name, const std::set<std::string>& known,
    std::map<std::string, std::string, std::less<>>* pointers = nullptr);

// Adds --config to `app`, for the options `app` has at this point (but --help, --version and
// --config itself). `file_name` labels errors: CLI11 hands the reader only a stream.
void add_config_option(CLI::App& app, std::string file_name);

// An error about the value of the flag `flag` ("--state-dir"), located where that value came
// from: in the config file ("FILE: /state_dir: message") when the file set it, else by the flag
// ("--state-dir: message"), which is also what a default is named by.
util::Error option_error(const CLI::App& app, std::string_view flag, std::string message);

// CLI11's message `message` for a value it refused ("--max-connections: Value 0 not in range
// ..."), moved to the config file and key when the file set that option; else unchanged.
std::string locate_refused_value(const CLI::App& app, const std::string& message);

class JsonConfig : public CLI::Config {
 public:
  // `known` holds the long option names (without dashes) the file may set; `app`, when given,
  // is the command line the file is read for, which tells which options the command line set.
  JsonConfig(std::string file_name, std::set<std::string> known, const CLI::App* app = nullptr);

  std::string to_config(const CLI::App*, bool, bool, std::string) const override;
  // read_config_items, its errors thrown as one CLI::ConfigError (a line each).
  std::vector<CLI::ConfigItem> from_config(std::istream& input) const override;

  // The JSON Pointer of the key ("/state_dir", as the file spells it) that set the option
  // `long_name` ("state-dir"), when the file's value is the one in force (the command line did
  // not set it: flags win); "" otherwise.
  std::string pointer_of(std::string_view long_name) const;
  const std::string& file_name() const { return file_name_; }

 private:
  std::string file_name_;
  std::set<std::string> known_;
  const CLI::App* app_;
  // Filled by from_config, which CLI11 declares const; written only while main's thread parses.
  mutable std::map<std::string, std::string, std::less<>> pointers_;
};

}  // namespace dtraced::cli
