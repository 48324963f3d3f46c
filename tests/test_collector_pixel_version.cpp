// The collector leases only to workers of its own pixel version (protocol::kPixelVersion) and
// refuses tiles that name another, so that one image never holds two renderers' pixels.
#include <string>

#include <catch2/catch.hpp>

#include "collector_testing.h"
#include "protocol/worker_messages.h"

namespace {

using namespace dtraced::testing;

const std::string kLeaseBody = R"({"worker": "w", "threads": 1})";

Request lease_with(std::string_view version) {
  Request req = make(Verb::post, "/v1/lease", kLeaseBody);
  req.erase(boost::beast::string_view(protocol::kPixelVersionHeader.data(), protocol::kPixelVersionHeader.size()));
  if (!version.empty()) req.set(protocol::kPixelVersionHeader, version);
  return req;
}

}  // namespace

TEST_CASE("a lease needs this build's pixel version", "[collector][pixel_version]") {
  TempDir dir;
  Harness h(dir);
  h.submit();
  const std::string other = std::to_string(protocol::kPixelVersion + 1);
  for (const std::string_view version : {std::string_view(), std::string_view(other), std::string_view("1x"),
                                         std::string_view("0"), std::string_view("99999999999")}) {
    INFO("header '" << version << "'");
    const Response res = h.collector.handle_sync(lease_with(version));
    REQUIRE(res.result() == Status::conflict);
    const protocol::ErrorBody e = error_of(res);
    CHECK(e.error.find(std::string(protocol::kPixelVersionHeader)) != std::string::npos);
    CHECK(e.error.find(fmt::format("pixel version {}", protocol::kPixelVersion)) != std::string::npos);
  }
  CHECK(h.metrics().counters.pixel_version_refusals == 5);
  CHECK(h.metrics().queue.leases == 0);
  // The refusal names what the worker sent.
  CHECK(error_of(h.collector.handle_sync(lease_with(other))).error.find("renders pixel version " + other) !=
        std::string::npos);
  // With the right version, the same request is leased a tile.
  const Response ok = h.collector.handle_sync(lease_with(std::to_string(protocol::kPixelVersion)));
  REQUIRE(ok.result() == Status::ok);
  auto reply = protocol::decode_lease_reply(ok.body());
  REQUIRE(reply.ok());
  CHECK(std::holds_alternative<protocol::Lease>(reply.value()));
}

TEST_CASE("a tile that names another pixel version is refused and offered again", "[collector][pixel_version]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const std::optional<protocol::Lease> l = h.lease();
  REQUIRE(l);
  const std::string target = fmt::format("/v1/jobs/{}/tiles/{}", job, l->tile);

  Request stale = make(Verb::put, target, payload(job, l->tile, l->rect));
  stale.set(protocol::kPixelVersionHeader, std::to_string(protocol::kPixelVersion + 1));
  const Response refused = h.collector.handle_sync(std::move(stale));
  REQUIRE(refused.result() == Status::conflict);
  CHECK(error_of(refused).error.find("renders pixel version") != std::string::npos);
  CHECK(h.status(job).tiles_done == 0);
  CHECK(h.metrics().counters.pixel_version_refusals == 1);

  // The same pixels with this version (or, from a tool, with none) are stored.
  Request current = make(Verb::put, target, payload(job, l->tile, l->rect));
  current.set(protocol::kPixelVersionHeader, std::to_string(protocol::kPixelVersion));
  REQUIRE(h.collector.handle_sync(std::move(current)).result() == Status::ok);
  CHECK(h.status(job).tiles_done == 1);
}
