#include "gateway/units/passthrough.h"

#include <algorithm>
#include <array>
#include <stdexcept>

#include <spdlog/spdlog.h>

#include "gateway/bus/bus_engine.h"
#include "gateway/modbus_tcp/tcp_serving.h"
#include "gateway/service/modbus_request.h"
#include "gateway/units/bus_faults.h"

namespace sms::gateway {

namespace {

namespace fc = function_code;
constexpr std::uint8_t kBroadcastSlave = 0;
constexpr std::uint8_t kMaxSlave = 247;

// Functions that only read: a broadcast of them is pointless (nobody answers).
constexpr std::array<std::uint8_t, 6> kReadFunctions{
    fc::kReadCoils,          fc::kReadDiscreteInputs,         fc::kReadHoldingRegisters,
    fc::kReadInputRegisters, fc::kReadWriteMultipleRegisters, fc::kReportServerId};

// What the client is told for a broadcast write: the answer the slave would have given.
struct BroadcastAnswerRule {
  std::uint8_t function;
  std::size_t answer_bytes;  // the request's first N bytes; 0: the whole request (echo)
};
constexpr std::array<BroadcastAnswerRule, 4> kBroadcastAnswers{{
    {fc::kWriteSingleCoil, 5},
    {fc::kWriteSingleRegister, 5},
    {fc::kWriteMultipleCoils, 5},
    {fc::kWriteMultipleRegisters, 5},
}};

bool is_read_function(std::uint8_t function) {
  return std::find(kReadFunctions.begin(), kReadFunctions.end(), function) != kReadFunctions.end();
}

Priority priority_of(std::uint8_t function) {
  return is_read_function(function) ? Priority::ClientRead : Priority::ClientWrite;
}

}  // namespace

std::optional<Bytes> broadcast_answer(std::span<const std::uint8_t> pdu) {
  if (pdu.empty() || is_read_function(pdu[0])) return std::nullopt;
  for (const auto& rule : kBroadcastAnswers) {
    if (rule.function == pdu[0] && pdu.size() >= rule.answer_bytes) {
      return Bytes(pdu.begin(), pdu.begin() + static_cast<std::ptrdiff_t>(rule.answer_bytes));
    }
  }
  return Bytes(pdu.begin(), pdu.end());
}

void forward_pdu(BusEngine& engine, std::uint8_t slave, std::span<const std::uint8_t> pdu, const PostFn& post,
                 const Reply& reply, const std::string& label, BroadcastReply broadcast_reply,
                 MotionEpoch motion_epoch) {
  if (pdu.empty()) return;  // the MBAP reader never hands over an empty PDU
  const std::uint8_t function = pdu[0];
  std::optional<Bytes> broadcast;
  if (slave == kBroadcastSlave) {
    broadcast = broadcast_answer(pdu);
    if (!broadcast) {
      spdlog::debug("passthrough: {}: FC{:02X} cannot be broadcast (nobody answers a read)", label, function);
      reply.send(exception_response(function, ModbusException::GatewayPathUnavailable));
      return;
    }
  }
  const bool silent = broadcast && broadcast_reply == BroadcastReply::None;
  Completion done =
      on_io_thread(post, [reply, function, label, silent, broadcast = std::move(broadcast)](BusResult result) {
        if (result.status != BusStatus::Ok) {
          spdlog::debug("passthrough: {} FC{:02X}: {}", label, function, result.detail);
          // A broadcast's client expects no answer: an exception would be taken for the next one's.
          if (silent) return reply.finish_without_answer();
          reply.send(exception_response(function, fault_from(result.status)));
          return;
        }
        if (silent) return reply.finish_without_answer();
        if (broadcast) {
          reply.send(*broadcast);
        } else {
          reply.send(std::move(result.data));
        }
      });
  try {
    engine.submit(RawPduOp{slave, Bytes(pdu.begin(), pdu.end()), motion_epoch}, priority_of(function), std::move(done));
  } catch (const std::invalid_argument& error) {
    // A PDU the line cannot carry (over 253 bytes cannot come from MBAP; kept for safety).
    spdlog::warn("passthrough: {}: {}", label, error.what());
    reply.send(exception_response(function, ModbusException::IllegalDataValue));
  }
}

ForwardHandler::ForwardHandler(BusEngine& engine, PostFn post, BroadcastReply broadcast_reply)
    : engine_(engine), post_(std::move(post)), broadcast_reply_(broadcast_reply) {}

void ForwardHandler::handle(std::uint8_t unit_id, std::span<const std::uint8_t> pdu, Reply reply) {
  if (pdu.empty()) return;
  if (unit_id > kMaxSlave) {
    reply.send(exception_response(pdu[0], ModbusException::GatewayPathUnavailable));
    return;
  }
  forward_pdu(engine_, unit_id, pdu, post_, reply,
              unit_id == kBroadcastSlave ? std::string("broadcast") : "slave " + std::to_string(unit_id),
              broadcast_reply_);
}

class ForwardGateway::Impl {
 public:
  explicit Impl(ForwardOptions options) : options_(std::move(options)) {}
  ~Impl() { stop(std::chrono::seconds{5}); }

  void start() {
    if (started_) throw std::logic_error("ForwardGateway::start called twice");
    started_ = true;
    BusSettings settings;
    settings.name = "forward";
    settings.protocol = protocol::BusProtocol::ModbusRtu;
    settings.serial = options_.serial;
    settings.response_timeout = options_.response_timeout;
    settings.retries = options_.retries;
    settings.queue_depth = options_.queue_depth;
    settings.discover = false;
    settings.poll = false;
    engine_ = make_bus_engine(std::move(settings), options_.rtu);
    handler_ = std::make_unique<ForwardHandler>(
        *engine_, [this](std::function<void()> work) { serving_.post(std::move(work)); }, options_.broadcast_reply);
    TcpServerOptions server_options;
    server_options.host = options_.listen.host;
    server_options.port = options_.listen.port;
    server_options.max_connections = options_.max_connections;
    server_options.idle_timeout = options_.idle_timeout;
    serving_.listen(server_options, *handler_);  // a port in use fails before the serial line is touched
    engine_->start();
    serving_.run();
  }

  void stop(std::chrono::milliseconds grace) {
    if (!started_ || stopped_) return;
    stopped_ = true;
    serving_.drain(grace);
    if (engine_) engine_->stop();
    serving_.stop();
  }

  std::uint16_t port() const { return serving_.port(); }
  BusEngine& engine() {
    if (!engine_) throw std::logic_error("ForwardGateway::engine before start()");
    return *engine_;
  }

 private:
  ForwardOptions options_;
  std::unique_ptr<BusEngine> engine_;
  std::unique_ptr<ForwardHandler> handler_;
  TcpServing serving_;  // last: destroyed first, so no connection outlives the handler
  bool started_ = false;
  bool stopped_ = false;
};

ForwardGateway::ForwardGateway(ForwardOptions options) : impl_(std::make_unique<Impl>(std::move(options))) {}
ForwardGateway::~ForwardGateway() = default;
void ForwardGateway::start() { impl_->start(); }
void ForwardGateway::stop(std::chrono::milliseconds grace) { impl_->stop(grace); }
std::uint16_t ForwardGateway::port() const { return impl_->port(); }
BusEngine& ForwardGateway::engine() { return impl_->engine(); }

}  // namespace sms::gateway
