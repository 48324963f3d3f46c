// dtraced::cli JSON config files for CLI11.
//
// `--config FILE` takes a JSON object whose keys are the long flag names in snake_case
// ("state_dir" for --state-dir) and whose values are strings, numbers, booleans or arrays of
// those. CLI11 applies them only to options not given on the command line, so flags win.
// Unknown keys, nested objects and nulls are errors that name the file and the key.
// Stateless apart from its construction arguments: thread-safe.
#pragma once

#include <set>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

namespace dtraced::cli {

class JsonConfig : public CLI::Config {
 public:
  // `known` holds the long option names (without dashes) the file may set.
  JsonConfig(std::string file_name, std::set<std::string> known);

  std::string to_config(const CLI::App*, bool, bool, std::string) const override;
  std::vector<CLI::ConfigItem> from_config(std::istream& input) const override;

 private:
  std::string file_name_;
  std::set<std::string> known_;
};

// Config files are small; anything larger is a mistake.
inline constexpr std::size_t kMaxConfigBytes = 1 << 20;

}  // namespace dtraced::cli
