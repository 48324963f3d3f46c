// A Beast message serialised by Beast's own serializer, driven synchronously into a string: the
// bytes bhttp::async_write would put on the wire, for writers that send a message as one buffer
// (one TLS record, one write) instead of through async_write's composed operations. Used by the
// server for small answers and by the load generator for its requests.
//
// Thread safety: a pure function of its arguments.
#pragma once

#include <string>

#include <boost/beast/core/buffers_range.hpp>
#include <boost/beast/http/message.hpp>
#include <boost/beast/http/serializer.hpp>
#include <boost/system/error_code.hpp>

namespace dtraced::http {

// Appends `message` as Beast serialises it to `out`; false (with `out` holding part of it) when
// the serializer fails.
template <bool isRequest, typename Body, typename Fields>
bool append_serialised(boost::beast::http::message<isRequest, Body, Fields>& message, std::string& out) {
  boost::beast::http::serializer<isRequest, Body, Fields> sr{message};
  boost::system::error_code ec;
  while (!ec && !sr.is_done()) {
    sr.next(ec, [&](boost::system::error_code&, const auto& buffers) {
      for (const auto b : boost::beast::buffers_range_ref(buffers)) {
        out.append(static_cast<const char*>(b.data()), b.size());
      }
      sr.consume(boost::beast::buffer_bytes(buffers));
    });
  }
  return !ec;
}

}  // namespace dtraced::http
