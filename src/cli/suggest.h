// dtraced::cli suggestions: "did you mean" for a misspelt verb or flag.
//
// CLI11 answers an unknown verb or flag with "The following argument was not expected: X" and
// nothing more. These functions add the nearest verb or flag of the command where X appeared
// (by jsonio's edit distance, as for unknown keys in scenes and config files), and a hint for
// the seed's flags (-vpw, -vph, -spl), which no spelling distance connects to dtraced's.
//
// Pure functions over a parsed (or failed) CLI11 App that is not modified meanwhile: call them on
// main's thread, after parsing.
#pragma once

#include <span>
#include <string>
#include <string_view>

#include <CLI/CLI.hpp>

namespace dtraced::cli {

// The one of `candidates` nearest to `word`, or "" when none is near enough to be what was meant
// (at most two edits, and fewer edits than `word` has characters).
std::string nearest_name(std::string_view word, std::span<const std::string> candidates);

// For each argument CLI11 could not place, in `app` or in one of its parsed subcommands, a line
// "ARG: did you mean CANDIDATE?" (none when nothing is near). Candidates are the verbs of the
// command where ARG appeared when ARG does not start with '-', else that command's flags.
std::string suggest_for_unexpected(const CLI::App& app);

// CLI11's failure message for `e`, with suggest_for_unexpected's lines after the error's own
// line. Install with `app.failure_message(failure_message_with_suggestions)`.
std::string failure_message_with_suggestions(const CLI::App* app, const CLI::Error& e);

}  // namespace dtraced::cli
