// The bundled trained model (models/small-synthetic) whose quality the tests here check.
#pragma once

#include <string>

namespace epona::test {

inline const std::string kBundledModel = std::string(EPONA_MODELS_DIR) + "/small-synthetic";

}  // namespace epona::test
