// The flags of `dtraced bench error` (cli/bench_error.h).
#pragma once

#include <string>

namespace dtraced::cli {

struct BenchErrorArgs {
  std::string scene;
};

}  // namespace dtraced::cli
