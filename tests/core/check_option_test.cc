// The one option check (core/check_option.h): each macro names the struct, the field, its value
// and the bound it violates, lets the values at its bound through, and refuses NaN.
#include "core/check_option.h"

#include <gtest/gtest.h>

#include <limits>
#include <string>
#include <utility>
#include <vector>

namespace holocap {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

struct ExampleOptions {
  double weight = 0.5;    // >= 0
  double step = 1;        // > 0
  double fraction = 0.5;  // < 1
  double angle_deg = 45;  // <= 90
  double exponent = 2;    // == 2
  double ratio = 0.5;     // in [0, 1]
  double depth_min_m = 0.2;
  double depth_max_m = 4;  // > depth_min_m
  int grid = 32;           // a power of two
  std::string scene = "auto";
  std::vector<double> scales = {1};
  int threads = 0;  // >= 0 (0: all cores)

  void Check() const;
};

void ExampleOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(weight, 0);
  HOLOCAP_CHECK_OPTION_GT(step, 0);
  HOLOCAP_CHECK_OPTION_LT(fraction, 1);
  HOLOCAP_CHECK_OPTION_LE(angle_deg, 90);
  HOLOCAP_CHECK_OPTION_EQ(exponent, 2);
  HOLOCAP_CHECK_OPTION_IN(ratio, 0, 1);
  HOLOCAP_CHECK_OPTION_GT(depth_max_m, depth_min_m);
  HOLOCAP_CHECK_OPTION(grid > 0 && (grid & (grid - 1)) == 0, grid, "a power of two");
  HOLOCAP_CHECK_OPTION(IsOneOf(scene, {"auto", "static"}), scene);
  for (double scale : scales) HOLOCAP_CHECK_OPTION(scale > 0, scales, "each positive");
  HOLOCAP_CHECK_OPTION_GE(threads, 0, "0: all cores");
}

// A check outside an Options::Check(): the message has no struct to name.
void CheckWeight(double weight) { HOLOCAP_CHECK_OPTION_GE(weight, 0); }

// The OptionError that `options.Check()` throws (a failed expectation when it throws none).
OptionError Refusal(const ExampleOptions& options) {
  try {
    options.Check();
  } catch (const OptionError& e) {
    return e;
  }
  ADD_FAILURE() << "Check() accepted the options";
  return OptionError("", "", "", "", "");
}

template <typename Change>
ExampleOptions With(Change change) {
  ExampleOptions options;
  change(options);
  return options;
}

TEST(CheckOption, EachMacroNamesTheFieldItsValueAndTheViolatedBound) {
  struct Case {
    ExampleOptions options;
    std::string field, message;
  };
  const std::vector<Case> cases = {
      {With([](auto& o) { o.weight = -1; }), "weight",
       "ExampleOptions::weight = -1 violates weight >= 0"},
      {With([](auto& o) { o.step = 0; }), "step", "ExampleOptions::step = 0 violates step > 0"},
      {With([](auto& o) { o.fraction = 1; }), "fraction",
       "ExampleOptions::fraction = 1 violates fraction < 1"},
      {With([](auto& o) { o.angle_deg = 90.5; }), "angle_deg",
       "ExampleOptions::angle_deg = 90.5 violates angle_deg <= 90"},
      {With([](auto& o) { o.exponent = 3; }), "exponent",
       "ExampleOptions::exponent = 3 violates exponent == 2"},
      {With([](auto& o) { o.ratio = 1.25; }), "ratio",
       "ExampleOptions::ratio = 1.25 violates ratio in [0, 1]"},
      {With([](auto& o) { o.ratio = -0.25; }), "ratio",
       "ExampleOptions::ratio = -0.25 violates ratio in [0, 1]"},
      {With([](auto& o) { o.depth_max_m = 0.1; }), "depth_max_m",
       "ExampleOptions::depth_max_m = 0.1 violates depth_max_m > depth_min_m (0.2)"},
      {With([](auto& o) { o.grid = 48; }), "grid",
       "ExampleOptions::grid = 48 violates grid > 0 && (grid & (grid - 1)) == 0 (a power of "
       "two)"},
      {With([](auto& o) { o.scene = "dynamic"; }), "scene",
       "ExampleOptions::scene = 'dynamic' violates IsOneOf(scene, {\"auto\", \"static\"})"},
      {With([](auto& o) {
         o.scales = {1, -2};
       }),
       "scales", "ExampleOptions::scales = [1, -2] violates scale > 0 (each positive)"},
      {With([](auto& o) { o.threads = -1; }), "threads",
       "ExampleOptions::threads = -1 violates threads >= 0 (0: all cores)"},
  };
  for (const Case& c : cases) {
    const OptionError e = Refusal(c.options);
    EXPECT_EQ(e.what(), c.message);
    EXPECT_EQ(e.options(), "ExampleOptions") << c.message;
    EXPECT_EQ(e.field(), c.field) << c.message;
  }
}

TEST(CheckOption, ValuesAtTheirClosedBoundsPass) {
  EXPECT_NO_THROW(ExampleOptions{}.Check());
  EXPECT_NO_THROW(With([](auto& o) {
                    o.weight = 0;
                    o.angle_deg = 90;
                    o.ratio = 0;
                    o.threads = 0;
                  }).Check());
  EXPECT_NO_THROW(With([](auto& o) {
                    o.fraction = 0.999999;
                    o.step = 1e-300;
                    o.ratio = 1;
                    o.grid = 1;
                    o.scene = "static";
                  }).Check());
}

TEST(CheckOption, NaNFailsEveryNumericCheck) {
  const std::vector<std::pair<std::string, ExampleOptions>> cases = {
      {"weight", With([](auto& o) { o.weight = kNaN; })},
      {"step", With([](auto& o) { o.step = kNaN; })},
      {"fraction", With([](auto& o) { o.fraction = kNaN; })},
      {"angle_deg", With([](auto& o) { o.angle_deg = kNaN; })},
      {"exponent", With([](auto& o) { o.exponent = kNaN; })},
      {"ratio", With([](auto& o) { o.ratio = kNaN; })},
      {"depth_max_m", With([](auto& o) { o.depth_max_m = kNaN; })},
      // A NaN bound fails the field compared with it.
      {"depth_max_m", With([](auto& o) { o.depth_min_m = kNaN; })},
      {"scales", With([](auto& o) {
         o.scales = {1, kNaN};
       })},
  };
  for (const auto& [field, options] : cases) {
    const OptionError e = Refusal(options);
    EXPECT_EQ(e.field(), field) << e.what();
    EXPECT_NE(std::string(e.what()).find("nan"), std::string::npos) << e.what();
  }
  EXPECT_STREQ(Refusal(With([](auto& o) { o.weight = kNaN; })).what(),
               "ExampleOptions::weight = nan violates weight >= 0");
}

TEST(CheckOption, InfinityFailsAFiniteUpperBound) {
  EXPECT_STREQ(Refusal(With([](auto& o) { o.angle_deg = kInf; })).what(),
               "ExampleOptions::angle_deg = inf violates angle_deg <= 90");
  EXPECT_STREQ(Refusal(With([](auto& o) { o.ratio = -kInf; })).what(),
               "ExampleOptions::ratio = -inf violates ratio in [0, 1]");
}

TEST(CheckOption, TheErrorKeepsItsPartsForTheCommandLine) {
  const OptionError e = Refusal(With([](auto& o) { o.threads = -3; }));
  EXPECT_EQ(e.value(), "-3");
  EXPECT_EQ(e.constraint(), "threads >= 0");
  EXPECT_EQ(e.explanation(), "0: all cores");
  EXPECT_EQ(e.NamedAs("--threads -3"), "--threads -3 violates threads >= 0 (0: all cores)");
  // An OptionError is an Error: callers that catch Error still do.
  EXPECT_THROW(With([](auto& o) { o.weight = -1; }).Check(), Error);
}

TEST(CheckOption, OutsideAnOptionsCheckTheMessageNamesTheFieldAlone) {
  try {
    CheckWeight(-2);
    FAIL() << "accepted a negative weight";
  } catch (const OptionError& e) {
    EXPECT_EQ(e.options(), "");
    EXPECT_STREQ(e.what(), "weight = -2 violates weight >= 0");
  }
}

TEST(CheckOption, ALongValueIsCut) {
  ExampleOptions options;
  options.scales.assign(100, 0.125);
  options.scales.back() = -1;
  const OptionError e = Refusal(options);
  EXPECT_EQ(e.value().substr(0, 14), "[0.125, 0.125,");
  EXPECT_LE(e.value().size(), 83u);
  EXPECT_EQ(e.value().substr(e.value().size() - 3), "...");
}

}  // namespace
}  // namespace holocap
