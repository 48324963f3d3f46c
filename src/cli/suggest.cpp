#include "cli/suggest.h"

#include <algorithm>
#include <cstddef>
#include <functional>
#include <limits>
#include <vector>

#include <fmt/format.h>

#include "jsonio/edit_distance.h"

namespace dtraced::cli {

namespace {

// The seed's render flags, one dash and several letters, which CLI11 reads as an unknown short
// flag: spelling distance would never lead from "-vpw" to "--width".
struct SeedFlag {
  std::string_view seed;
  std::string_view meant;
};
constexpr SeedFlag kSeedFlags[] = {{"-vpw", "--width"}, {"-vph", "--height"}, {"-spl", "--samples"}};

// "--name" and "-n" for every flag of `app`.
std::vector<std::string> flag_names(const CLI::App& app) {
  std::vector<std::string> names;
  for (const CLI::Option* opt : app.get_options()) {
    for (const std::string& l : opt->get_lnames()) names.push_back("--" + l);
    for (const std::string& s : opt->get_snames()) names.push_back("-" + s);
  }
  return names;
}

std::vector<std::string> verb_names(const CLI::App& app) {
  std::vector<std::string> names;
  for (const CLI::App* sub : app.get_subcommands(std::function<bool(const CLI::App*)>{})) {
    if (!sub->get_name().empty()) names.push_back(sub->get_name());
  }
  return names;
}

// The line for one argument `arg` that `app` could not place, or "".
std::string suggestion(const CLI::App& app, const std::string& arg) {
  if (!arg.starts_with("-")) {
    const std::string verb = nearest_name(arg, verb_names(app));
    return verb.empty() ? "" : fmt::format("{}: did you mean {}?\n", arg, verb);
  }
  // "--flag=value": the name is what was misspelt.
  const std::string name = arg.substr(0, arg.find('='));
  const std::vector<std::string> flags = flag_names(app);
  for (const SeedFlag& s : kSeedFlags) {
    if (name == s.seed && std::find(flags.begin(), flags.end(), s.meant) != flags.end()) {
      return fmt::format("{}: did you mean {}? (the seed's {} is dtraced's {})\n", name, s.meant, s.seed, s.meant);
    }
  }
  const std::string flag = nearest_name(name, flags);
  return flag.empty() ? "" : fmt::format("{}: did you mean {}?\n", name, flag);
}

}  // namespace

std::string nearest_name(std::string_view word, std::span<const std::string> candidates) {
  std::string_view best;
  std::size_t best_distance = std::numeric_limits<std::size_t>::max();
  for (const std::string& c : candidates) {
    const std::size_t d = jsonio::edit_distance(word, c);
    if (d < best_distance) {
      best_distance = d;
      best = c;
    }
  }
  // The rule jsonio uses for keys: two edits catch a transposition ("--sampels") or a letter
  // too many or too few, and a word of two letters is never "near" anything.
  if (best_distance <= 2 && best_distance < word.size()) return std::string(best);
  return {};
}

std::string suggest_for_unexpected(const CLI::App& app) {
  std::string out;
  for (const std::string& arg : app.remaining(/*recurse=*/false)) out += suggestion(app, arg);
  for (const CLI::App* sub : app.get_subcommands()) out += suggest_for_unexpected(*sub);
  return out;
}

std::string failure_message_with_suggestions(const CLI::App* app, const CLI::Error& e) {
  std::string text = CLI::FailureMessage::simple(app, e);
  if (dynamic_cast<const CLI::ExtrasError*>(&e) == nullptr) return text;
  const std::size_t first_line = text.find('\n') + 1;
  return text.insert(first_line, suggest_for_unexpected(*app));
}

}  // namespace dtraced::cli
