// dtraced::http's short names for Asio and Beast, shared by the server's and the client's .cpp
// files: one spelling of each, and the one completion token (async::kAwaitTuple) they await with.
//
// Thread safety: names only.
#pragma once

#include <boost/asio/ip/tcp.hpp>
#include <boost/system/error_code.hpp>

#include "async/async.h"

namespace dtraced::http::names {

namespace net = async::net;
namespace beast = boost::beast;
namespace bhttp = boost::beast::http;
using async::kAwaitTuple;
using tcp = net::ip::tcp;
using boost::system::error_code;

}  // namespace dtraced::http::names
