// The avatar kinds each program can open, registered as the drivers are (app/drivers.cpp): a
// new kind is its folder and one line here.
#include "app/commands.h"
#include "avatar/avatar.h"
#include "splat/splat.h"

#if HOLOCAP_WITH_NEURAL
#include "neural/live_rerender.h"
#include "neural/neural.h"
#include "neural/rerender.h"
#endif

namespace holocap {

void RegisterAvatarKinds() {
  AvatarKindRegistry& registry = AvatarKindRegistry::Global();
  RegisterSplatAvatarKind(registry);
#if HOLOCAP_WITH_NEURAL
  RegisterNeuralVolumeAvatarKind(registry);
  RegisterRerenderAvatarKind(registry);
  RegisterLiveRerenderAvatarKind(registry);
#endif
}

}  // namespace holocap
