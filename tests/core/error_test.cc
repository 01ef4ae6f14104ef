#include "core/error.h"

#include <gtest/gtest.h>

#include <cstdio>

namespace holocap {
namespace {

// A garbage file quoted in an error sent its binary bytes to the terminal.
TEST(Error, PrintableEscapesControlAndInvalidBytesAndKeepsUtf8) {
  EXPECT_EQ(Printable("plain text: 'a b'"), "plain text: 'a b'");
  EXPECT_EQ(Printable(std::string("a\nb\tc\rd\x1b[2J\x7f", 12)), "a\\nb\\tc\\rd\\x1b[2J\\x7f");
  EXPECT_EQ(Printable(std::string("\0\xff\xfe", 3)), "\\x00\\xff\\xfe");
  EXPECT_EQ(Printable("caf\xc3\xa9 \xe2\x82\xac"), "caf\xc3\xa9 \xe2\x82\xac");  // é €
  // A truncated, an overlong and a surrogate sequence are not UTF-8.
  EXPECT_EQ(Printable("\xc3"), "\\xc3");
  EXPECT_EQ(Printable("\xc0\xaf"), "\\xc0\\xaf");
  EXPECT_EQ(Printable("\xed\xa0\x80"), "\\xed\\xa0\\x80");
  for (int byte = 0; byte < 256; ++byte) {
    for (char c : Printable(std::string(1, static_cast<char>(byte))))
      EXPECT_TRUE(c >= 0x20 && c < 0x7f) << byte;
  }
}

TEST(Error, CaptureStderrReturnsWhatWasPrintedAndRestoresStderr) {
  ::testing::internal::CaptureStderr();
  std::string captured = CaptureStderr([] {
    std::fprintf(stderr, "parser.re(162): first\n");
    std::fprintf(stderr, "second line\n");
  });
  EXPECT_EQ(captured, "parser.re(162): first; second line");
  std::fprintf(stderr, "after\n");
  EXPECT_EQ(::testing::internal::GetCapturedStderr(), "after\n");
  EXPECT_THROW(CaptureStderr([] {
                 std::fprintf(stderr, "x\n");
                 Fail("thrown");
               }),
               Error);
}

}  // namespace
}  // namespace holocap
