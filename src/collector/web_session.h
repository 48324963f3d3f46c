// dtraced::collector web sessions: who signed in to the web page, in memory only.
//
// Owns: the session store behind the page's cookie (docs/web-access.md). Signing in with the
// farm's bearer token (or a viewer's or client's credential) creates a session: a random id (32 bytes from OpenSSL's
// RAND_bytes, 64 hex digits: the cookie) and a random CSRF token (the same size: the page sends it back in a header on
// every request that changes state). The store keeps only the SHA-256 digest of each id, so its memory never holds a
// usable cookie. Sessions live for `lifetime` from sign-in; at most `max_sessions` are kept (signing in past the cap
// drops the oldest). A collector restart signs everyone out.
//
// Also SignInLimiter: failed sign-ins in a sliding window; past the limit every sign-in is
// refused (429) until the window has room again, so the token cannot be guessed quickly.
//
// Pure: no sockets, no logging, no clock reads (every call takes `now`); only RAND_bytes.
//
// Thread safety: none. One owner (the collector's event loop) calls everything.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <map>
#include <optional>
#include <string>
#include <string_view>

#include "collector/credentials.h"
#include "collector/queue.h"
#include "util/sha256.h"

namespace dtraced::collector {

struct SessionLimits {
  std::size_t max_sessions = 64;
  Duration lifetime = std::chrono::hours(12);
};

// 32 random bytes as 64 lowercase hex digits: a session id and a CSRF token have this form.
inline constexpr std::size_t kSessionSecretHex = 64;

class SessionStore {
 public:
  explicit SessionStore(SessionLimits limits = {}) : limits_(limits) {}

  struct Created {
    std::string id;    // the cookie's value
    std::string csrf;  // the X-Dtraced-CSRF header's value
  };
  // A new session from `now` for `who` (the token that signed in: the operator's by default);
  // nullopt when the system's random source fails.
  std::optional<Created> create(TimePoint now, Principal who = Principal{"", Role::kOperator});

  struct Live {
    std::string csrf;
    Duration remaining{};  // until it expires
    Principal who;         // who signed in (admission re-checks a credential is not revoked)
  };
  // The live session of cookie value `id`, or nullopt (unknown, malformed or expired).
  std::optional<Live> find(std::string_view id, TimePoint now) const;

  // Whether `csrf` is the CSRF token of the live session `id` (compared in constant time).
  bool csrf_matches(std::string_view id, std::string_view csrf, TimePoint now) const;

  // Signs a session out; false when there was none.
  bool remove(std::string_view id);

  // Drops the expired sessions.
  void sweep(TimePoint now);

  std::size_t size() const { return sessions_.size(); }
  const SessionLimits& limits() const { return limits_; }

 private:
  struct Session {
    std::string csrf;
    TimePoint created;
    Principal who;
  };
  std::optional<util::Sha256Digest> key_of(std::string_view id) const;

  SessionLimits limits_;
  std::map<util::Sha256Digest, Session> sessions_;  // by the SHA-256 of the id
};

// At most `max_failures` failed sign-ins in any `window`; past that, sign-ins are refused.
class SignInLimiter {
 public:
  explicit SignInLimiter(std::size_t max_failures = 10, Duration window = std::chrono::minutes(1))
      : max_(max_failures), window_(window) {}
  // Whether a sign-in may be tried at `now`.
  bool allows(TimePoint now);
  // A sign-in failed at `now`.
  void failed(TimePoint now);
  // How long until a sign-in is allowed again (zero when it is).
  Duration retry_after(TimePoint now);

 private:
  void forget_old(TimePoint now);
  std::size_t max_;
  Duration window_;
  std::deque<TimePoint> failures_;  // at most max_ + 1, oldest first
};

// Whether `s` is kSessionSecretHex lowercase hex digits.
bool is_session_secret(std::string_view s);

}  // namespace dtraced::collector
