#include "web/assets.h"

namespace dtraced::web {

const Asset* find_asset(std::string_view url_path) {
  for (const Asset& asset : all_assets()) {
    if (asset.url_path == url_path) return &asset;
  }
  return nullptr;
}

}  // namespace dtraced::web
