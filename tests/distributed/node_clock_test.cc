// A capture host's clock state, as a node reports it.
#include <gtest/gtest.h>

#include <set>

#include "core/error.h"
#include "distributed/node.h"

namespace holocap {
namespace {

TEST(NodeClock, ClockStateSaysWhereItCameFrom) {
  const ClockState state = ReadClockState();
  EXPECT_FALSE(state.host.empty());
  EXPECT_TRUE((std::set<std::string>{"ptp", "chrony", "adjtimex"}.count(state.source)))
      << state.source << ": " << state.detail;
  EXPECT_NE(state.detail.find(state.source == "ptp"      ? "ptp"
                              : state.source == "chrony" ? "chronyc"
                                                         : "adjtimex"),
            std::string::npos)
      << state.detail;
  if (state.source == "adjtimex") {
    EXPECT_GE(state.error_ns, 0);
  }
  const ClockState back = ClockState::FromJson(state.ToJson());
  EXPECT_EQ(back.source, state.source);
  EXPECT_EQ(back.offset_ns, state.offset_ns);
  EXPECT_EQ(back.synchronised, state.synchronised);
}

TEST(NodeClock, OptionsAreChecked) {
  NodeCaptureOptions options;
  options.out = "take";
  EXPECT_THROW(options.Check(), Error);  // neither frames nor seconds
  options.seconds = 2;
  EXPECT_NO_THROW(options.Check());
  options.reply_timeout_s = 0;
  EXPECT_THROW(options.Check(), Error);
  CaptureNodeOptions node;
  node.listen = "";
  EXPECT_THROW(node.Check(), Error);
}

}  // namespace
}  // namespace holocap
