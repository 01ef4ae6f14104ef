#include "capture/aravis/fake_gige_camera.h"

#include <arpa/inet.h>
#include <arv.h>
#include <fcntl.h>
#include <ifaddrs.h>
#include <net/if.h>
#include <netinet/in.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <sys/signalfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <deque>
#include <random>
#include <vector>

#include "core/error.h"

namespace holocap {

// Plain checks: this file is also the standalone fake camera program, which links no holocap
// library (HOLOCAP_CHECK_OPTION_* lives in holocap_core).
void FakeGigeCameraSpec::Check() const {
  if (address.empty()) Fail("fake GigE camera: no address");
  // The GigE Vision bootstrap registers hold the serial in 16 bytes, NUL included.
  if (serial.empty() || serial.size() > 15)
    Fail("fake GigE camera: serial must have 1..15 characters");
  if (!(lost_per_thousand >= 0 && lost_per_thousand <= 1000)) {
    Fail("fake GigE camera: lost_per_thousand must be 0..1000");
  }
  // The camera sleeps whole microseconds between ticks.
  if (!(trigger_tick_hz > 0 && trigger_tick_hz <= 1e5))
    Fail("fake GigE camera: trigger_tick_hz must be in (0, 1e5]");
  if (pattern != "ramp" && pattern != "noise")
    Fail("fake GigE camera: pattern must be ramp or noise (not '", pattern, "')");
  if (peer != "holocap" && peer != "libaravis")
    Fail("fake GigE camera: peer must be holocap or libaravis (not '", peer, "')");
}

namespace {

// ArvFakeCameraFillPattern: every byte of the frame from a xorshift generator that runs on
// from frame to frame.
void FillNoise(ArvBuffer* buffer, void* state, guint32, guint32, ArvPixelFormat pixel_format) {
  // The buffer's received size is still 0 here: the image's own size says what to fill.
  const size_t size = static_cast<size_t>(arv_buffer_get_image_width(buffer)) *
                      arv_buffer_get_image_height(buffer) *
                      ARV_PIXEL_FORMAT_BIT_PER_PIXEL(pixel_format) / 8;
  auto* data = static_cast<uint8_t*>(const_cast<void*>(arv_buffer_get_data(buffer, nullptr)));
  uint64_t& x = *static_cast<uint64_t*>(state);
  for (size_t i = 0; i < size; i += 8) {
    x ^= x << 13;
    x ^= x >> 7;
    x ^= x << 17;
    for (size_t k = 0; k < 8 && i + k < size; ++k) data[i + k] = static_cast<uint8_t>(x >> (8 * k));
  }
}

// SIGTERM and SIGINT, blocked for the whole process before any thread exists.
sigset_t BlockStopSignals() {
  sigset_t stop_signals;
  sigemptyset(&stop_signals);
  sigaddset(&stop_signals, SIGTERM);
  sigaddset(&stop_signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &stop_signals, nullptr);
  return stop_signals;
}

// ---- GigE Vision 1.2 wire layouts (all fields big-endian) ----
//
// GVCP command: key 0x42, flags, command, length of what follows, request id; then the command's
// data. Acknowledge: status (0 = success; 0x8xxx an error), answer (command + 1), length, the
// request's id; then the answer's data.
constexpr uint16_t kGvcpPort = 3956;
constexpr uint8_t kGvcpCommandKey = 0x42;
constexpr uint8_t kGvcpFlagExtendedIds = 0x10;
constexpr size_t kGvcpHeader = 8;
constexpr size_t kGvcpDataMax = 540;  // the largest READMEM block a host may ask for is 536 bytes
enum : uint16_t {
  kDiscoveryCmd = 0x0002,
  kPacketResendCmd = 0x0040,
  kReadRegCmd = 0x0080,
  kWriteRegCmd = 0x0082,
  kReadMemCmd = 0x0084,
  kWriteMemCmd = 0x0086,
};
enum : uint16_t {
  kStatusSuccess = 0x0000,
  kStatusNotImplemented = 0x8001,
  kStatusInvalidParameter = 0x8002,
  kStatusInvalidAddress = 0x8003,
  kStatusAccessDenied = 0x8006,
};
// Bootstrap registers (GigE Vision 1.2, table 28).
constexpr uint32_t kBootstrapDiscoverySize =
    0xf8;  // version .. user-defined name: the discovery answer
constexpr uint32_t kRegTimestampTickHigh = 0x093c;
constexpr uint32_t kRegTimestampTickLow = 0x0940;
constexpr uint32_t kRegControlChannelPrivilege = 0x0a00;
// GVSP packet: status, block id (16 bits), packet format (8 bits) and packet id (24 bits); then
// the leader, payload or trailer data. Each payload packet carries the stream channel's packet
// size less IP (20), UDP (8) and this header (8) bytes, so the host places it by packet id alone.
constexpr size_t kGvspHeader = 8;
constexpr size_t kGvspOverhead = 20 + 8 + kGvspHeader;
constexpr uint8_t kGvspLeader = 0x01, kGvspTrailer = 0x02, kGvspPayload = 0x03;
constexpr uint16_t kGvspPayloadImage = 0x0001;

void Put16(uint8_t* p, uint16_t v) {
  p[0] = static_cast<uint8_t>(v >> 8);
  p[1] = static_cast<uint8_t>(v);
}
void Put32(uint8_t* p, uint32_t v) {
  Put16(p, static_cast<uint16_t>(v >> 16));
  Put16(p + 2, static_cast<uint16_t>(v));
}
uint16_t Get16(const uint8_t* p) { return static_cast<uint16_t>(p[0] << 8 | p[1]); }
uint32_t Get32(const uint8_t* p) { return static_cast<uint32_t>(Get16(p)) << 16 | Get16(p + 2); }
uint64_t Get64(const uint8_t* p) { return static_cast<uint64_t>(Get32(p)) << 32 | Get32(p + 4); }

void PutGvspHeader(uint8_t* p, uint16_t block_id, uint8_t format, uint32_t packet_id) {
  Put16(p, 0);
  Put16(p + 2, block_id);
  Put32(p + 4, static_cast<uint32_t>(format) << 24 | (packet_id & 0xffffff));
}

// One frame as sent: everything needed to send any of its packets again.
struct SentFrame {
  uint16_t block_id = 0;
  uint64_t timestamp_ticks = 0;
  uint32_t pixel_format = 0, width = 0, height = 0, x_offset = 0, y_offset = 0;
  size_t packet_data = 0;  // image bytes per payload packet
  std::vector<uint8_t> image;

  uint32_t payload_packets() const {
    return static_cast<uint32_t>((image.size() + packet_data - 1) / packet_data);
  }
  uint32_t packets() const { return payload_packets() + 2; }  // leader, payload..., trailer

  // Writes packet `id` (0 leader, 1..n payload, n + 1 trailer) into `out`; returns its size.
  size_t Packet(uint32_t id, uint8_t* out) const {
    const uint32_t n = payload_packets();
    if (id == 0) {
      PutGvspHeader(out, block_id, kGvspLeader, 0);
      uint8_t* d = out + kGvspHeader;
      Put16(d, 0);  // reserved
      Put16(d + 2, kGvspPayloadImage);
      Put32(d + 4, static_cast<uint32_t>(timestamp_ticks >> 32));
      Put32(d + 8, static_cast<uint32_t>(timestamp_ticks));
      Put32(d + 12, pixel_format);
      Put32(d + 16, width);
      Put32(d + 20, height);
      Put32(d + 24, x_offset);
      Put32(d + 28, y_offset);
      Put16(d + 32, 0);  // padding x
      Put16(d + 34, 0);  // padding y
      return kGvspHeader + 36;
    }
    if (id <= n) {
      PutGvspHeader(out, block_id, kGvspPayload, id);
      const size_t offset = (id - 1) * packet_data;
      const size_t size = std::min(packet_data, image.size() - offset);
      std::memcpy(out + kGvspHeader, image.data() + offset, size);
      return kGvspHeader + size;
    }
    PutGvspHeader(out, block_id, kGvspTrailer, n + 1);
    Put16(out + kGvspHeader, 0);  // reserved
    Put16(out + kGvspHeader + 2, kGvspPayloadImage);
    Put32(out + kGvspHeader + 4, height);  // size y
    return kGvspHeader + 8;
  }
};

int BindUdp(in_addr_t address, uint16_t port, bool shared) {
  const int fd = socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return -1;
  if (shared) {
    // Every camera on the host listens for broadcast discovery on the same port (as GLib's
    // g_socket_bind with allow_reuse does for libaravis' cameras).
    const int one = 1;
    setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
    setsockopt(fd, SOL_SOCKET, SO_REUSEPORT, &one, sizeof(one));
  }
  sockaddr_in where{};
  where.sin_family = AF_INET;
  where.sin_addr.s_addr = address;
  where.sin_port = htons(port);
  if (bind(fd, reinterpret_cast<sockaddr*>(&where), sizeof(where)) != 0) {
    close(fd);
    return -1;
  }
  return fd;
}

class GigePeer {
 public:
  GigePeer(const FakeGigeCameraSpec& spec, ArvFakeCamera* camera)
      : spec_(spec),
        camera_(camera),
        drop_(spec.lost_per_thousand / 1000.0),
        rng_(std::hash<std::string>{}(spec.serial)) {}
  ~GigePeer() {
    for (int fd : fds_) close(fd);
    if (gvsp_ >= 0) close(gvsp_);
    if (image_ != nullptr) g_object_unref(image_);
  }

  // Binds the control, discovery and stream sockets; false when the address is not local.
  bool Bind() {
    in_addr address{};
    if (inet_pton(AF_INET, spec_.address.c_str(), &address) != 1) return false;
    ifaddrs* interfaces = nullptr;
    if (getifaddrs(&interfaces) != 0) return false;
    bool found = false;
    in_addr_t broadcast = INADDR_NONE;
    for (ifaddrs* i = interfaces; i != nullptr; i = i->ifa_next) {
      if (i->ifa_addr == nullptr || i->ifa_addr->sa_family != AF_INET ||
          (i->ifa_flags & IFF_UP) == 0)
        continue;
      if (reinterpret_cast<sockaddr_in*>(i->ifa_addr)->sin_addr.s_addr != address.s_addr) continue;
      found = true;
      if ((i->ifa_flags & IFF_BROADCAST) != 0 && i->ifa_broadaddr != nullptr) {
        broadcast = reinterpret_cast<sockaddr_in*>(i->ifa_broadaddr)->sin_addr.s_addr;
      }
      break;
    }
    freeifaddrs(interfaces);
    if (!found) return false;
    GInetAddress* inet = g_inet_address_new_from_bytes(
        reinterpret_cast<const guint8*>(&address.s_addr), G_SOCKET_FAMILY_IPV4);
    arv_fake_camera_set_inet_address(camera_, inet);
    g_object_unref(inet);
    const int control = BindUdp(address.s_addr, kGvcpPort, false);
    gvsp_ = BindUdp(address.s_addr, 0, false);
    if (control < 0 || gvsp_ < 0) {
      if (control >= 0) close(control);
      return false;
    }
    fds_.push_back(control);
    const int global = BindUdp(INADDR_BROADCAST, kGvcpPort, true);
    if (global >= 0) fds_.push_back(global);
    if (broadcast != INADDR_NONE && broadcast != address.s_addr) {
      const int subnet = BindUdp(broadcast, kGvcpPort, true);
      if (subnet >= 0) fds_.push_back(subnet);
    }
    for (int fd : fds_) fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK);
    return true;
  }

  // Serves until a signal arrives on `signal_fd`.
  void Run(int signal_fd) {
    std::vector<pollfd> polled;
    for (int fd : fds_) polled.push_back({fd, POLLIN, 0});
    polled.push_back({signal_fd, POLLIN, 0});
    while (true) {
      const bool active = Active();
      int64_t deadline_us = g_get_real_time() + 100000;
      if (active) {
        guint64 next_us = 0;
        arv_fake_camera_get_sleep_time_for_next_frame(camera_, &next_us);
        deadline_us = static_cast<int64_t>(next_us);
      }
      bool tick = false;
      while (true) {
        const int64_t left_us = deadline_us - g_get_real_time();
        if (left_us <= 0) {
          tick = true;
          break;
        }
        const timespec timeout{static_cast<time_t>(left_us / 1000000),
                               static_cast<long>(left_us % 1000000) * 1000};
        for (auto& p : polled) p.revents = 0;
        if (ppoll(polled.data(), polled.size(), &timeout, nullptr) < 0 && errno != EINTR) return;
        if (polled.back().revents != 0) return;  // SIGTERM or SIGINT
        for (size_t i = 0; i + 1 < polled.size(); ++i) {
          if (polled[i].revents != 0) Receive(polled[i].fd);
        }
        if (Active() != active) break;  // acquisition started or stopped: a new schedule
      }
      if (!Active()) {
        StopStream();
        continue;
      }
      if (!tick) continue;
      if (arv_fake_camera_is_in_free_running_mode(camera_) ||
          (arv_fake_camera_is_in_software_trigger_mode(camera_) &&
           arv_fake_camera_check_and_acknowledge_software_trigger(camera_))) {
        SendFrame();
      }
    }
  }

 private:
  bool Active() {
    return arv_fake_camera_get_control_channel_privilege(camera_) != 0 &&
           arv_fake_camera_get_acquisition_status(camera_) != 0;
  }

  uint32_t Register(uint32_t address) {
    guint32 value = 0;
    arv_fake_camera_read_register(camera_, address, &value);
    return value;
  }

  void StopStream() {
    streaming_ = false;
    history_.clear();
  }

  // Fills the next frame from the camera model and sends it, leaving packets out at the asked
  // ratio; the frame is kept for resend requests.
  void SendFrame() {
    if (!streaming_) {
      GSocketAddress* address = arv_fake_camera_get_stream_address(camera_);
      const bool ok = g_socket_address_to_native(address, &stream_to_, sizeof(stream_to_), nullptr);
      g_object_unref(address);
      if (!ok || stream_to_.sin_port == 0) return;
      const size_t payload = arv_fake_camera_get_payload(camera_);
      if (image_ == nullptr || payload != image_size_) {
        if (image_ != nullptr) g_object_unref(image_);
        image_ = arv_buffer_new(payload, nullptr);
        image_size_ = payload;
      }
      // The last frames' packets stay available: more frames for small images, at most 64 MB.
      history_frames_ =
          std::clamp<size_t>((size_t{64} << 20) / std::max<size_t>(payload, 1), 2, 16);
      const uint64_t tick_hz = static_cast<uint64_t>(Register(kRegTimestampTickHigh)) << 32 |
                               Register(kRegTimestampTickLow);
      tick_hz_ = tick_hz > 0 ? tick_hz : 1000000000;
      streaming_ = true;
    }
    guint32 packet_size = 0;
    arv_fake_camera_fill_buffer(camera_, image_, &packet_size);
    if (arv_buffer_get_status(image_) != ARV_BUFFER_STATUS_SUCCESS) return;
    SentFrame frame;
    frame.block_id = static_cast<uint16_t>(arv_buffer_get_frame_id(image_));
    frame.timestamp_ticks = static_cast<uint64_t>(
        static_cast<unsigned __int128>(arv_buffer_get_timestamp(image_)) * tick_hz_ / 1000000000u);
    frame.pixel_format = arv_buffer_get_image_pixel_format(image_);
    gint x = 0, y = 0, width = 0, height = 0;
    arv_buffer_get_image_region(image_, &x, &y, &width, &height);
    frame.x_offset = static_cast<uint32_t>(x);
    frame.y_offset = static_cast<uint32_t>(y);
    frame.width = static_cast<uint32_t>(width);
    frame.height = static_cast<uint32_t>(height);
    frame.packet_data = packet_size > kGvspOverhead ? packet_size - kGvspOverhead : 1400;
    const auto* data = static_cast<const uint8_t*>(arv_buffer_get_data(image_, nullptr));
    frame.image.assign(data, data + image_size_);
    history_.push_back(std::move(frame));
    while (history_.size() > history_frames_) history_.pop_front();
    const SentFrame& sent = history_.back();
    std::bernoulli_distribution dropped(drop_);
    for (uint32_t id = 0; id < sent.packets(); ++id) {
      if (drop_ > 0 && dropped(rng_)) continue;
      Send(sent, id);
    }
  }

  void Send(const SentFrame& frame, uint32_t id) {
    if (scratch_.size() < kGvspHeader + frame.packet_data + 64)
      scratch_.resize(kGvspHeader + frame.packet_data + 64);
    const size_t size = frame.Packet(id, scratch_.data());
    sendto(gvsp_, scratch_.data(), size, 0, reinterpret_cast<const sockaddr*>(&stream_to_),
           sizeof(stream_to_));
  }

  void Receive(int fd) {
    uint8_t in[2048];
    while (true) {
      sockaddr_in from{};
      socklen_t from_size = sizeof(from);
      const ssize_t got =
          recvfrom(fd, in, sizeof(in), 0, reinterpret_cast<sockaddr*>(&from), &from_size);
      if (got < 0) return;
      if (got >= static_cast<ssize_t>(kGvcpHeader)) Handle(fd, from, in, static_cast<size_t>(got));
    }
  }

  bool IsController(const sockaddr_in& from) {
    if (!has_controller_) return true;
    const auto now = std::chrono::steady_clock::now();
    if (now - controller_seen_ >
        std::chrono::milliseconds(arv_fake_camera_get_heartbeat_timeout(camera_))) {
      // The controller's heartbeat stopped: the camera is free again.
      has_controller_ = false;
      arv_fake_camera_set_control_channel_privilege(camera_, 0);
      return true;
    }
    return from.sin_addr.s_addr == controller_.sin_addr.s_addr &&
           from.sin_port == controller_.sin_port;
  }

  void Handle(int fd, const sockaddr_in& from, const uint8_t* in, size_t size) {
    if (in[0] != kGvcpCommandKey) return;
    const uint8_t flags = in[1];
    const uint16_t command = Get16(in + 2);
    const size_t length = std::min<size_t>(Get16(in + 4), size - kGvcpHeader);
    const uint16_t request = Get16(in + 6);
    const uint8_t* data = in + kGvcpHeader;
    uint8_t out[kGvcpHeader + kGvcpDataMax];
    size_t answer = 0;
    uint16_t status = kStatusSuccess;
    const bool may_write = IsController(from);
    switch (command) {
      case kDiscoveryCmd:
        arv_fake_camera_read_memory(camera_, 0, kBootstrapDiscoverySize, out + kGvcpHeader);
        answer = kBootstrapDiscoverySize;
        break;
      case kReadRegCmd:
        for (size_t i = 0; i + 4 <= length && answer + 4 <= kGvcpDataMax; i += 4) {
          const uint32_t address = Get32(data + i);
          guint32 value = 0;  // as libaravis' peer: a register outside the model reads 0
          arv_fake_camera_read_register(camera_, address, &value);
          Put32(out + kGvcpHeader + answer, value);
          answer += 4;
          if (address == kRegControlChannelPrivilege && has_controller_ &&
              from.sin_addr.s_addr == controller_.sin_addr.s_addr &&
              from.sin_port == controller_.sin_port) {
            controller_seen_ = std::chrono::steady_clock::now();  // the controller's heartbeat
          }
        }
        break;
      case kWriteRegCmd: {
        uint16_t written = 0;
        for (size_t i = 0; i + 8 <= length; i += 8) {
          const uint32_t address = Get32(data + i);
          if (!may_write) {
            status = kStatusAccessDenied;
            break;
          }
          arv_fake_camera_write_register(camera_, address, Get32(data + i + 4));
          ++written;
        }
        Put16(out + kGvcpHeader, 0);
        Put16(out + kGvcpHeader + 2, written);
        answer = 4;
        break;
      }
      case kReadMemCmd: {
        if (length < 8) {
          status = kStatusInvalidParameter;
          break;
        }
        const uint32_t address = Get32(data);
        const uint16_t count = Get16(data + 6);
        if (count > kGvcpDataMax - 4) {
          status = kStatusInvalidParameter;
          break;
        }
        Put32(out + kGvcpHeader, address);
        if (!arv_fake_camera_read_memory(camera_, address, count, out + kGvcpHeader + 4)) {
          status = kStatusInvalidAddress;
          break;
        }
        answer = 4 + count;
        break;
      }
      case kWriteMemCmd: {
        const uint32_t address = length >= 4 ? Get32(data) : 0;
        const size_t count = length >= 4 ? length - 4 : 0;
        if (!may_write) {
          status = kStatusAccessDenied;
        } else if (length < 4 || !arv_fake_camera_write_memory(
                                     camera_, address, static_cast<guint32>(count), data + 4)) {
          status = kStatusInvalidAddress;
        }
        Put16(out + kGvcpHeader, 0);
        Put16(out + kGvcpHeader + 2, status == kStatusSuccess ? static_cast<uint16_t>(count) : 0);
        answer = 4;
        break;
      }
      case kPacketResendCmd:
        Resend(flags, data, length);
        return;  // answered on the stream channel, never acknowledged
      default:
        status = kStatusNotImplemented;
        break;
    }
    if (status != kStatusSuccess) answer = 0;
    Put16(out, status);
    Put16(out + 2, static_cast<uint16_t>(command + 1));
    Put16(out + 4, static_cast<uint16_t>(answer));
    Put16(out + 6, request);
    sendto(fd, out, kGvcpHeader + answer, 0, reinterpret_cast<const sockaddr*>(&from),
           sizeof(from));
    // Taking or giving up the control channel privilege makes (or unmakes) the controller.
    const bool privileged = arv_fake_camera_get_control_channel_privilege(camera_) != 0;
    if (!has_controller_ && privileged) {
      has_controller_ = true;
      controller_ = from;
      controller_seen_ = std::chrono::steady_clock::now();
    } else if (has_controller_ && !privileged) {
      has_controller_ = false;
    }
  }

  // PACKETRESEND: stream channel (16 bits), block id (16 bits), first and last packet id (24
  // bits each); with extended ids: stream channel, reserved, first and last packet id (32 bits),
  // then the 64-bit block id. Packets of a frame no longer kept are not sent.
  void Resend(uint8_t flags, const uint8_t* data, size_t length) {
    if (!streaming_ || length < 12) return;
    uint64_t block_id = Get32(data) & 0xffff;
    uint32_t first = Get32(data + 4) & 0xffffff, last = Get32(data + 8) & 0xffffff;
    if ((flags & kGvcpFlagExtendedIds) != 0) {
      if (length < 20) return;
      first = Get32(data + 4);
      last = Get32(data + 8);
      block_id = Get64(data + 12);
    }
    for (const SentFrame& frame : history_) {
      if (frame.block_id != block_id) continue;
      for (uint32_t id = first; id <= last && id < frame.packets(); ++id) Send(frame, id);
      return;
    }
  }

  const FakeGigeCameraSpec& spec_;
  ArvFakeCamera* camera_;
  double drop_;
  std::mt19937_64 rng_;
  std::vector<int> fds_;  // control, then broadcast discovery
  int gvsp_ = -1;
  bool has_controller_ = false;
  sockaddr_in controller_{};
  std::chrono::steady_clock::time_point controller_seen_;
  bool streaming_ = false;
  sockaddr_in stream_to_{};
  ArvBuffer* image_ = nullptr;
  size_t image_size_ = 0;
  uint64_t tick_hz_ = 1000000000;
  size_t history_frames_ = 2;
  std::deque<SentFrame> history_;
  std::vector<uint8_t> scratch_;
};

int ServeHolocapPeer(const FakeGigeCameraSpec& spec, const sigset_t& stop_signals,
                     uint64_t* noise_state) {
  const int signal_fd = signalfd(-1, &stop_signals, SFD_CLOEXEC);
  if (signal_fd < 0) return 2;
  ArvFakeCamera* camera = arv_fake_camera_new(spec.serial.c_str());
  arv_fake_camera_set_trigger_frequency(camera, spec.trigger_tick_hz);
  if (spec.pattern == "noise") arv_fake_camera_set_fill_pattern(camera, &FillNoise, noise_state);
  int status = 3;
  {
    GigePeer peer(spec, camera);
    if (peer.Bind()) {
      status = 0;
      peer.Run(signal_fd);
    }
  }
  g_object_unref(camera);
  close(signal_fd);
  return status;
}

int ServeLibaravisPeer(const FakeGigeCameraSpec& spec, const sigset_t& stop_signals,
                       uint64_t* noise_state) {
  ArvGvFakeCamera* camera =
      arv_gv_fake_camera_new_full(spec.address.c_str(), spec.serial.c_str(), nullptr);
  if (camera == nullptr) return 2;
  g_object_set(camera, "gvsp-lost-ratio", spec.lost_per_thousand / 1000.0, nullptr);
  ArvFakeCamera* fake = arv_gv_fake_camera_get_fake_camera(camera);
  arv_fake_camera_set_trigger_frequency(fake, spec.trigger_tick_hz);
  if (spec.pattern == "noise") arv_fake_camera_set_fill_pattern(fake, &FillNoise, noise_state);
  int status = 0;
  if (arv_gv_fake_camera_is_running(camera)) {
    int signal = 0;
    sigwait(&stop_signals, &signal);
  } else {
    status = 3;
  }
  g_object_unref(camera);
  return status;
}

}  // namespace

int ServeFakeGigeCamera(const FakeGigeCameraSpec& spec) {
  spec.Check();
  // Blocked before any thread exists, so that only the camera's own wait receives them.
  const sigset_t stop_signals = BlockStopSignals();
  uint64_t noise_state = 0x9e3779b97f4a7c15ull;
  if (spec.peer == "libaravis") return ServeLibaravisPeer(spec, stop_signals, &noise_state);
  return ServeHolocapPeer(spec, stop_signals, &noise_state);
}

std::string FakeGigeCameraProgram() { return HOLOCAP_FAKE_GIGE_CAMERA_PROGRAM; }

}  // namespace holocap
