#include "core/rig.h"

#include <gtest/gtest.h>

#include <fstream>

#include "core/error.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;

std::filesystem::path WriteText(const TempDir& dir, const std::string& name,
                                const std::string& text) {
  auto file = dir / name;
  std::ofstream(file) << text;
  return file;
}

std::string ErrorOf(const std::filesystem::path& file) {
  try {
    RigDescription::Load(file);
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

TEST(RigDescription, LoadsYamlAndJsonAlike) {
  TempDir dir;
  auto yaml = WriteText(dir, "rig.yaml", R"(
name: booth
sync: hardware
fps: 60
sensors:
  - {name: cam0, uri: "aravis:Fake_1", exposure_us: 4000}
  - name: depth0
    uri: v4l2:/dev/video2
    role: depth
    paired_with: cam0
    options: {format: Z16}
)");
  RigDescription rig = RigDescription::Load(yaml);
  EXPECT_EQ(rig.name, "booth");
  EXPECT_EQ(rig.sync, SyncMode::kHardwareTrigger);
  EXPECT_EQ(rig.fps, 60);
  ASSERT_EQ(rig.sensors.size(), 2u);
  EXPECT_EQ(rig.sensors[0].scheme(), "aravis");
  EXPECT_EQ(rig.sensors[0].exposure_us, 4000);
  EXPECT_EQ(rig.sensor("depth0").role, SensorRole::kDepth);
  EXPECT_EQ(rig.sensor("depth0").options["format"], "Z16");
  auto json = WriteText(dir, "rig.json", rig.ToJson().dump());
  RigDescription again = RigDescription::Load(json);
  EXPECT_EQ(again.ToJson(), rig.ToJson());
}

TEST(RigDescription, MalformedFilesNameTheProblem) {
  TempDir dir;
  EXPECT_NE(ErrorOf(WriteText(dir, "a.yaml", "sensors: [ {name: a, uri: sim:x#a "))
                .find("not valid YAML"),
            std::string::npos);
  EXPECT_NE(ErrorOf(WriteText(dir, "b.yaml", "name: x\n")).find("'sensors'"), std::string::npos);
  EXPECT_NE(ErrorOf(WriteText(dir, "c.yaml", "sensors: [{name: a}]")).find("'uri' is missing"),
            std::string::npos);
  EXPECT_NE(ErrorOf(WriteText(dir, "d.yaml",
                              "sensors: [{name: a, uri: 'sim:x'}, {name: a, uri: 'sim:y'}]"))
                .find("twice"),
            std::string::npos);
  EXPECT_NE(ErrorOf(WriteText(dir, "e.yaml", "sensors: [{name: a, uri: 'sim:x', role: infrared}]"))
                .find("unknown sensor role"),
            std::string::npos);
  EXPECT_NE(
      ErrorOf(WriteText(dir, "f.yaml", "sensors: [{name: a, uri: nocolon}]")).find("no scheme"),
      std::string::npos);
  EXPECT_NE(ErrorOf(WriteText(dir, "g.yaml", "fps: fast\nsensors: [{name: a, uri: 'sim:x'}]"))
                .find("'fps'"),
            std::string::npos);
  EXPECT_NE(ErrorOf(WriteText(dir, "h.json", "{\"sensors\": [")).find("not valid JSON"),
            std::string::npos);
  EXPECT_NE(ErrorOf(dir / "missing.yaml").find("does not exist"), std::string::npos);
  EXPECT_NE(ErrorOf(WriteText(dir, "i.yaml", "sensors: [{name: a, uri: 'sim:x', paired_with: b}]"))
                .find("not in the rig"),
            std::string::npos);
}

// yaml-cpp passes any bytes through; a rig's strings go into take.json, which must be UTF-8
// (found by fuzz_rig_yaml: `holocap capture` died in nlohmann's dump otherwise).
TEST(RigDescription, YamlStringsMustBeUtf8) {
  const std::string sensors = "\nsensors: [{name: cam0, uri: 'sim:x#cam0'}]\n";
  RigDescription rig = RigDescription::ParseYaml("name: caf\xc3\xa9" + sensors, "ok.yaml");
  EXPECT_EQ(rig.name, "caf\xc3\xa9");
  EXPECT_NO_THROW(rig.ToJson().dump());
  for (const std::string& bad : {"name: caf\xe9" + sensors, "\n\nname: \xed\xa0\x80" + sensors,
                                 "options: {\xff: 1}" + sensors}) {
    try {
      RigDescription::ParseYaml(bad, "bad.yaml");
      ADD_FAILURE() << bad;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("'bad.yaml' is not valid YAML: line "),
                std::string::npos)
          << e.what();
      EXPECT_NE(std::string(e.what()).find("not UTF-8"), std::string::npos) << e.what();
    }
  }
}

// Nested aliases ("billion laughs") expanded to 3.8 GB before bad_alloc; the expansion now
// stops at kMaxRigYamlValues with the file's name. A sensor named ".." wrote its frames into
// the take's root; names are plain file names.
TEST(RigDescription, NestedAliasesAndPathNamesAreRefused) {
  std::string laughs = "a: &a [x, x, x, x, x, x, x, x, x, x]\n";
  for (char c = 'b'; c <= 'i'; ++c) {
    laughs += Cat(c, ": &", c, " [");
    for (int k = 0; k < 10; ++k) laughs += Cat(k ? ", *" : "*", static_cast<char>(c - 1));
    laughs += "]\n";
  }
  laughs += "sensors: [{name: a, uri: 'sim:x'}]\n";
  try {
    RigDescription::ParseYaml(laughs, "laughs.yaml");
    ADD_FAILURE();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("'laughs.yaml' is not valid YAML: line "),
              std::string::npos)
        << e.what();
    EXPECT_NE(std::string(e.what()).find("expands to more than 200000 values"), std::string::npos)
        << e.what();
  }
  for (const std::string& name : {"'..'", "'.'", "'a\\nb'", "'a\\x01'"}) {
    try {
      RigDescription::ParseYaml(
          "sensors: [{name: \"" + name.substr(1, name.size() - 2) + "\", uri: 'sim:x'}]",
          "names.yaml");
      ADD_FAILURE() << name;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("may not be '.' or '..'"), std::string::npos)
          << e.what();
    }
  }
}

TEST(RigDescription, JsonNumbersItCannotHoldGiveAnError) {
  EXPECT_THROW(RigDescription::ParseJson("6E12644", "big.json"), Error);
  EXPECT_THROW(RigDescription::ParseJson("{\"fps\": 1e999, \"sensors\": []}", "big.json"), Error);
}

}  // namespace
}  // namespace holocap
