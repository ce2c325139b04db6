// fuzz/fuzz_pickle.cpp — the restricted unpickler on arbitrary bytes (every opcode, the memo,
// marks, globals allow-list, persistent ids, tensor rebuilds, nesting and size limits); an
// accepted document is walked completely and its state dict selected as load_torch_checkpoint does.
#include <set>
#include <utility>

#include "epona/io/pickle.hpp"
#include "epona/io/torch_checkpoint.hpp"
#include "fuzz_common.hpp"

namespace pickle_target {
using namespace epona::io::pickle;

// Visits every value reachable from `v` once, describing each (which reads every table entry).
// The memo can share a container many times (a DAG), hence `seen`; nesting is at most
// Limits::max_depth levels, so the recursion is bounded.
std::size_t walk(const Document& doc, const Value& v, std::set<std::pair<Kind, std::int64_t>>& seen) {
  std::size_t n = doc.describe(v).size();
  const bool container = v.kind == Kind::Tuple || v.kind == Kind::List || v.kind == Kind::Dict;
  if (container && !seen.emplace(v.kind, v.i).second) return n;
  switch (v.kind) {
    case Kind::Tuple:
    case Kind::List:
      for (const auto& x : doc.items(v)) n += walk(doc, x, seen);
      break;
    case Kind::Dict:
      for (const auto& [k, x] : doc.dict(v).items) n += walk(doc, k, seen) + walk(doc, x, seen);
      break;
    case Kind::Tensor: {
      const TensorRef& t = doc.tensor(v);
      epona_fuzz::require(t.shape.size() == t.stride.size(), "a tensor has one stride per dimension");
      n += doc.storage(t.storage).key.size();
      break;
    }
    default: break;
  }
  return n;
}
}  // namespace pickle_target

EPONA_FUZZ_TARGET(pickle) {
  using namespace pickle_target;
  return epona_fuzz::run([&] {
    const Document doc = unpickle(epona_fuzz::as_bytes(data, size), "fuzz.pkl");
    std::set<std::pair<Kind, std::int64_t>> seen;
    walk(doc, doc.root, seen);
    epona::io::torch_detail::select_state_dict(doc, "", "fuzz.pkl");
  });
}
