// dtraced::collector router: an admitted request to its handler.
//
// Owns: the two entry points the HTTP server calls. check_request_header runs admit() on a
// request's head before its body is read (a wrong token or an unknown route costs no body buffer;
// the body gets the route's own limit); handle_request admits again (for requests that reach it by
// other paths, such as tests), checks the body's size, and calls the route's handler (handlers.h).
// Counts the refused tokens and logs them (rate-limited, with the peer address); times leases;
// sweeps the worker registry (workers.h) as requests arrive.
//
// Thread safety: on the loop only.
#pragma once

#include <cstdint>
#include <optional>

#include "async/async.h"
#include "collector/context.h"
#include "http/types.h"

namespace dtraced::collector {

// The server's header check (http::Server::HeaderCheck).
std::optional<http::Response> check_request_header(Context& c, const http::Request& head, std::uint64_t& body_limit);

// The server's authenticated predicate (http::Server::Authenticated): the request carries a live
// credential's bearer token (or the operator's), so its connection keeps its slot under a flood
// of unauthenticated ones.
bool is_authenticated(const Context& c, const http::Request& head);

// The server's handler (http::Server::Handler).
async::Awaitable<http::Response> handle_request(Context& c, http::Request req);

}  // namespace dtraced::collector
