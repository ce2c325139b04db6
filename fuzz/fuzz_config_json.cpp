// fuzz/fuzz_config_json.cpp — parse_configs (both layouts, every key's type and range, validate()
// with its size limits) on arbitrary text; an accepted config must survive to_json -> parse
// unchanged.
#include "epona/domain/config_json.hpp"
#include "fuzz_common.hpp"

EPONA_FUZZ_TARGET(config_json) {
  return epona_fuzz::run([&] {
    const auto configs = epona::io::parse_configs(epona_fuzz::as_text(data, size), "fuzz.json");
    const auto again = epona::io::parse_configs(epona::io::to_json(configs).dump(), "round trip");
    epona_fuzz::require(again == configs, "to_json -> parse_configs gives back the same configs");
  });
}
