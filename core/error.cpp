#include "core/error.h"

#include <unistd.h>

#include <cstdio>
#include <cstdlib>

namespace holocap {
namespace {

// Length of the valid UTF-8 sequence starting at text[at] (0 if there is none): no overlong
// forms, no surrogates, nothing above U+10FFFF.
size_t Utf8Length(std::string_view text, size_t at) {
  const auto byte = [&](size_t i) { return static_cast<unsigned char>(text[i]); };
  const unsigned char lead = byte(at);
  size_t length = 0;
  unsigned char lo = 0x80, hi = 0xbf;
  if (lead >= 0xc2 && lead <= 0xdf) {
    length = 2;
  } else if (lead >= 0xe0 && lead <= 0xef) {
    length = 3;
    if (lead == 0xe0) lo = 0xa0;
    if (lead == 0xed) hi = 0x9f;
  } else if (lead >= 0xf0 && lead <= 0xf4) {
    length = 4;
    if (lead == 0xf0) lo = 0x90;
    if (lead == 0xf4) hi = 0x8f;
  } else {
    return 0;
  }
  if (at + length > text.size()) return 0;
  if (byte(at + 1) < lo || byte(at + 1) > hi) return 0;
  for (size_t i = 2; i < length; ++i) {
    if (byte(at + i) < 0x80 || byte(at + i) > 0xbf) return 0;
  }
  return length;
}

}  // namespace

std::string Printable(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (size_t at = 0; at < text.size();) {
    const unsigned char c = static_cast<unsigned char>(text[at]);
    if (c >= 0x20 && c < 0x7f) {
      out += static_cast<char>(c);
      ++at;
      continue;
    }
    if (size_t length = c >= 0x80 ? Utf8Length(text, at) : 0; length > 0) {
      out.append(text.substr(at, length));
      at += length;
      continue;
    }
    static constexpr char kHex[] = "0123456789abcdef";
    if (c == '\n') {
      out += "\\n";
    } else if (c == '\t') {
      out += "\\t";
    } else if (c == '\r') {
      out += "\\r";
    } else {
      out += "\\x";
      out += kHex[c >> 4];
      out += kHex[c & 15];
    }
    ++at;
  }
  return out;
}

std::string CaptureStderr(const std::function<void()>& call) {
  std::fflush(stderr);
  std::FILE* capture = std::tmpfile();
  const int saved = capture != nullptr ? ::dup(STDERR_FILENO) : -1;
  if (saved < 0 || ::dup2(::fileno(capture), STDERR_FILENO) < 0) {
    // Nowhere to capture to: the diagnostics stay on stderr.
    if (saved >= 0) ::close(saved);
    if (capture != nullptr) std::fclose(capture);
    call();
    return {};
  }
  struct Restore {
    int saved;
    ~Restore() {
      std::fflush(stderr);
      ::dup2(saved, STDERR_FILENO);
      ::close(saved);
    }
  };
  std::string text;
  {
    Restore restore{saved};
    try {
      call();
    } catch (...) {
      std::fclose(capture);
      throw;
    }
  }
  std::rewind(capture);
  char buffer[4096];
  size_t n = 0;
  while ((n = std::fread(buffer, 1, sizeof(buffer), capture)) > 0 && text.size() < (1 << 16))
    text.append(buffer, n);
  std::fclose(capture);
  std::string joined;
  size_t start = 0;
  while (start < text.size()) {
    size_t end = text.find('\n', start);
    if (end == std::string::npos) end = text.size();
    std::string_view line(text.data() + start, end - start);
    while (!line.empty() && (line.back() == '\r' || line.back() == ' ')) line.remove_suffix(1);
    if (!line.empty()) {
      if (!joined.empty()) joined += "; ";
      joined.append(line);
    }
    start = end + 1;
  }
  return joined;
}

}  // namespace holocap
