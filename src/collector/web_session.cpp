#include "collector/web_session.h"

#include <algorithm>
#include <array>

#include <openssl/crypto.h>
#include <openssl/rand.h>

namespace dtraced::collector {
namespace {

std::optional<std::string> random_hex() {
  std::array<unsigned char, kSessionSecretHex / 2> bytes{};
  if (RAND_bytes(bytes.data(), static_cast<int>(bytes.size())) != 1) return std::nullopt;
  constexpr char kDigits[] = "0123456789abcdef";
  std::string hex;
  hex.reserve(kSessionSecretHex);
  for (const unsigned char b : bytes) {
    hex += kDigits[b >> 4];
    hex += kDigits[b & 15];
  }
  return hex;
}

}  // namespace

bool is_session_secret(std::string_view s) {
  return s.size() == kSessionSecretHex &&
         std::all_of(s.begin(), s.end(), [](char c) { return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'); });
}

std::optional<util::Sha256Digest> SessionStore::key_of(std::string_view id) const {
  if (!is_session_secret(id)) return std::nullopt;
  return util::sha256_bytes(id);
}

std::optional<SessionStore::Created> SessionStore::create(TimePoint now, Principal who) {
  sweep(now);
  std::optional<std::string> id = random_hex();
  std::optional<std::string> csrf = random_hex();
  if (!id || !csrf) return std::nullopt;
  while (sessions_.size() >= limits_.max_sessions && !sessions_.empty()) {
    const auto oldest = std::min_element(sessions_.begin(), sessions_.end(), [](const auto& a, const auto& b) {
      return a.second.created < b.second.created;
    });
    sessions_.erase(oldest);
  }
  sessions_[util::sha256_bytes(*id)] = Session{*csrf, now, std::move(who)};
  return Created{std::move(*id), std::move(*csrf)};
}

std::optional<SessionStore::Live> SessionStore::find(std::string_view id, TimePoint now) const {
  const auto key = key_of(id);
  if (!key) return std::nullopt;
  const auto it = sessions_.find(*key);
  if (it == sessions_.end()) return std::nullopt;
  const TimePoint expires = it->second.created + limits_.lifetime;
  if (now >= expires) return std::nullopt;
  return Live{it->second.csrf, expires - now, it->second.who};
}

bool SessionStore::csrf_matches(std::string_view id, std::string_view csrf, TimePoint now) const {
  const std::optional<Live> live = find(id, now);
  if (!live || csrf.size() != live->csrf.size()) return false;
  return CRYPTO_memcmp(csrf.data(), live->csrf.data(), csrf.size()) == 0;
}

bool SessionStore::remove(std::string_view id) {
  const auto key = key_of(id);
  return key && sessions_.erase(*key) == 1;
}

void SessionStore::sweep(TimePoint now) {
  std::erase_if(sessions_, [&](const auto& s) { return now >= s.second.created + limits_.lifetime; });
}

void SignInLimiter::forget_old(TimePoint now) {
  while (!failures_.empty() && now - failures_.front() >= window_) failures_.pop_front();
}

bool SignInLimiter::allows(TimePoint now) {
  forget_old(now);
  return failures_.size() <= max_;
}

void SignInLimiter::failed(TimePoint now) {
  forget_old(now);
  failures_.push_back(now);
  while (failures_.size() > max_ + 1) failures_.pop_front();
}

Duration SignInLimiter::retry_after(TimePoint now) {
  forget_old(now);
  if (failures_.size() <= max_) return Duration::zero();
  // Room again once enough of the oldest failures leave the window.
  return failures_[failures_.size() - max_ - 1] + window_ - now;
}

}  // namespace dtraced::collector
