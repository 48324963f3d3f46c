// dtraced::cli configuration errors, named as the user wrote them.
//
// collector::check_collector_config and worker::validate name a problem by its field in the
// daemon's configuration ("state_dir", "timeouts.connect"), which the user never typed: they
// gave a flag (--state-dir) or a key in the --config file. These functions rename each problem
// to the flag, or to the file and JSON Pointer of the key when the file set the value
// (json_config.h's option_error). A field no flag sets keeps its name.
//
// Pure functions over a parsed CLI11 App: call them on main's thread, after parsing.
#pragma once

#include <string>

#include <CLI/CLI.hpp>

#include "util/result.h"

namespace dtraced::cli {

// The flag that sets the configuration field `field` of either role ("" when none does).
std::string flag_of_field(const std::string& field);

// `e` located by flag or config key: a field of either role's configuration (see flag_of_field)
// or a flag ("--listen") in e.path; other errors unchanged.
util::Error locate_role_error(const CLI::App& app, util::Error e);

// Every error of `errors`, located, one line each.
std::string located_errors_text(const CLI::App& app, const util::Errors& errors);

}  // namespace dtraced::cli
