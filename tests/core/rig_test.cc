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

}  // namespace
}  // namespace holocap
