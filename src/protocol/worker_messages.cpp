// GET /v1/workers and the worker's self-describing headers.
#include "protocol/worker_messages.h"

#include <algorithm>
#include <array>
#include <cfloat>
#include <charconv>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>

#include "jsonio/parse.h"
#include "protocol/codec.h"

namespace dtraced::protocol {
namespace {

namespace json = boost::json;
using namespace detail;

constexpr std::array<std::string_view, 2> kUploadAnswerKeys = {"result", "next"};
constexpr std::array<SubmitResult, 3> kSubmitResults = {SubmitResult::kStored, SubmitResult::kAlreadyDone,
                                                        SubmitResult::kJobGone};
constexpr std::array<std::string_view, 3> kWorkerListKeys = {"recent_window_s", "quiet_after_s", "workers"};
constexpr std::array<std::string_view, 14> kWorkerInfoKeys = {
    "name",   "peer",  "isa",        "threads",           "quiet",   "last_seen_s",  "first_seen_s",
    "leases", "tiles", "duplicates", "faulty_duplicates", "refused", "recent_tiles", "recent_rays"};
constexpr std::uint64_t kMaxCount = kMaxId;  // counts travel as JSON numbers

json::object worker_object(const WorkerInfo& w) {
  json::object o;
  o["name"] = w.name;
  o["peer"] = w.peer;
  o["isa"] = w.isa;
  o["threads"] = w.threads;
  o["quiet"] = w.quiet;
  o["last_seen_s"] = jsonio::exact_number(w.last_seen_s);
  o["first_seen_s"] = jsonio::exact_number(w.first_seen_s);
  o["leases"] = w.leases;
  o["tiles"] = w.tiles;
  o["duplicates"] = w.duplicates;
  o["faulty_duplicates"] = w.faulty_duplicates;
  o["refused"] = w.refused;
  o["recent_tiles"] = w.recent_tiles;
  o["recent_rays"] = w.recent_rays;
  return o;
}

void read_worker(Fields& f, WorkerInfo& w) {
  f.string("name", w.name, kMaxWorkerNameBytes);
  f.string("peer", w.peer, kMaxPeerBytes);
  f.string("isa", w.isa, kMaxIsaHeaderBytes);
  f.integer("threads", w.threads, 0, kMaxWorkerThreads);
  f.boolean("quiet", w.quiet);
  f.number("last_seen_s", w.last_seen_s, 0, DBL_MAX);
  f.number("first_seen_s", w.first_seen_s, 0, DBL_MAX);
  f.integer("leases", w.leases, 0, kMaxCount);
  f.integer("tiles", w.tiles, 0, kMaxCount);
  f.integer("duplicates", w.duplicates, 0, kMaxCount);
  f.integer("faulty_duplicates", w.faulty_duplicates, 0, kMaxCount);
  f.integer("refused", w.refused, 0, kMaxCount);
  f.integer("recent_tiles", w.recent_tiles, 0, kMaxCount);
  f.integer("recent_rays", w.recent_rays, 0, kMaxCount);
}

}  // namespace

std::optional<std::string> parse_isa_header(std::string_view value) {
  if (value.empty() || value.size() > kMaxIsaHeaderBytes) return std::nullopt;
  const bool ok = std::all_of(value.begin(), value.end(),
                              [](char c) { return (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_'; });
  if (!ok) return std::nullopt;
  return std::string(value);
}

std::optional<std::uint32_t> parse_pixel_version_header(std::string_view value) {
  std::uint32_t version = 0;
  const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), version);
  if (value.empty() || ec != std::errc() || end != value.data() + value.size() || version == 0) return std::nullopt;
  return version;
}

std::optional<std::uint64_t> parse_render_ms_header(std::string_view value) {
  std::uint64_t ms = 0;
  const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), ms);
  if (value.empty() || ec != std::errc() || end != value.data() + value.size() || ms > kMaxRenderMs) {
    return std::nullopt;
  }
  return ms;
}

std::optional<bool> parse_finished_header(std::string_view value) {
  if (value == "1") return true;
  if (value == "0") return false;
  return std::nullopt;
}

std::optional<std::uint32_t> parse_next_lease_header(std::string_view value) {
  std::uint32_t threads = 0;
  const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), threads);
  if (value.empty() || ec != std::errc() || end != value.data() + value.size() || threads == 0 ||
      threads > kMaxWorkerThreads) {
    return std::nullopt;
  }
  return threads;
}

std::string encode(const UploadAnswer& m) {
  if (!m.next) return encode(m.result);
  // The lease reply as POST /v1/lease writes it, spliced in: one encoder for both.
  std::string text = R"({"result":")";
  text += to_string(m.result);
  text += R"(","next":)";
  text += encode(*m.next);
  text += '}';
  return text;
}

Decoded<UploadAnswer> decode_upload_answer(std::string_view text) {
  return decode_object<UploadAnswer>(
      text, kMaxMessageBytes, kMaxMessageDepth, kUploadAnswerKeys, [](Fields& f, UploadAnswer& m) {
        std::string result;
        if (f.string("result", result, 32)) {
          const auto it = std::find_if(kSubmitResults.begin(), kSubmitResults.end(),
                                       [&](SubmitResult r) { return to_string(r) == result; });
          if (it == kSubmitResults.end()) {
            f.reader().error(f.path("result"), "must be stored, already_done or job_gone");
          } else {
            m.result = *it;
          }
        }
        // The next lease is read from the same parse, its errors at /next/...
        const json::value* next = f.get("next", Need::kOptional);
        if (next == nullptr) return;
        const jsonio::Path at = f.path("next");
        const json::object* o = f.reader().object(*next, at);
        if (o == nullptr) return;
        Fields nf(f.reader(), *o, at, kLeaseReplyKeys);
        LeaseReply reply;
        read_lease_reply(nf, reply);
        m.next = std::move(reply);
      });
}

std::string encode(const WorkerList& m) {
  json::array workers;
  workers.reserve(m.workers.size());
  for (const WorkerInfo& w : m.workers) workers.push_back(worker_object(w));
  json::object o;
  o["recent_window_s"] = jsonio::exact_number(m.recent_window_s);
  o["quiet_after_s"] = jsonio::exact_number(m.quiet_after_s);
  o["workers"] = std::move(workers);
  return jsonio::to_text(o);
}

Decoded<WorkerList> decode_worker_list(std::string_view text) {
  return decode_object<WorkerList>(
      text, kMaxWorkerListBytes, kMaxMessageDepth, kWorkerListKeys, [](Fields& f, WorkerList& m) {
        f.number("recent_window_s", m.recent_window_s, 0, DBL_MAX);
        f.number("quiet_after_s", m.quiet_after_s, 0, DBL_MAX);
        read_object_array(f, "workers", kMaxListedWorkers, kWorkerInfoKeys, m.workers, read_worker);
      });
}

}  // namespace dtraced::protocol
