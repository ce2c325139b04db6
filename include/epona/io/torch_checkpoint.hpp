// epona/io/torch_checkpoint.hpp — the tensors of an official PyTorch checkpoint (the .pkl/.pt that
// torch.save writes: a ZIP of "<archive>/data.pkl" plus one record "<archive>/data/<key>" per
// storage), as torch.load(path)[key] would give them, without Python: each tensor is a zero-copy
// view of its storage record in the memory-mapped file. Which dict is the state dict: the top-level
// dict if it holds tensors only, else "model_state_dict" (world model), "model" (temporal DC-AE),
// "state_dict", or an explicit key.
#pragma once

#include <algorithm>
#include <map>
#include <string>
#include <string_view>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/io/pickle.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/io/zip.hpp"

namespace epona::io {

struct TorchLoadOptions {
  std::string key;                // key of the state dict in the top-level dict; empty = automatic
  bool verify_checksums = false;  // CRC-32 of every storage record (reads the whole file once);
                                  // the pickle itself is always verified
};

namespace torch_detail {

inline constexpr const char* kStateDictKeys[] = {"model_state_dict", "model", "state_dict"};

// torch.save puts every record under one folder (the file's stem, or "archive"); the first
// entry names it, as PyTorch's own reader assumes.
inline std::string archive_prefix(const ZipArchive& zip) {
  EPONA_CHECK(!zip.entries().empty(), zip.name(), ": empty ZIP archive, not a torch.save checkpoint");
  const std::string& first = zip.entries().front().name;
  const auto slash = first.find('/');
  EPONA_CHECK(slash != std::string::npos && slash > 0, zip.name(),
              ": not a torch.save checkpoint (its first entry '", pickle::Document::printable(first),
              "' is not inside a folder)");
  return first.substr(0, slash + 1);
}

inline bool is_dict_of_tensors(const pickle::Document& doc, const pickle::Value& v) {
  if (v.kind != pickle::Kind::Dict || doc.dict(v).items.empty()) return false;
  for (const auto& [k, x] : doc.dict(v).items)
    if (x.kind != pickle::Kind::Tensor) return false;
  return true;
}

// "'model' (dict of 428 items), 'epoch' (int 3), ..." for messages.
inline std::string list_keys(const pickle::Document& doc, const pickle::Dict& d) {
  std::string s;
  std::size_t shown = 0;
  for (const auto& [k, v] : d.items) {
    if (shown == 30) {
      s += ", ... (" + std::to_string(d.items.size()) + " keys)";
      break;
    }
    s += (shown++ ? ", " : "") +
         (k.kind == pickle::Kind::String ? "'" + pickle::Document::printable(doc.str(k)) + "'" : doc.describe(k));
    s += " (" + doc.describe(v) + ")";
  }
  return s.empty() ? "none" : s;
}

// The dict whose tensors are returned (see the header comment for the rule).
inline pickle::Value select_state_dict(const pickle::Document& doc, const std::string& key,
                                       const std::string& source) {
  const pickle::Value& root = doc.root;
  EPONA_CHECK(root.kind == pickle::Kind::Dict, source, ": the checkpoint holds a ", doc.describe(root),
              ", expected a dict (a state dict, or a dict holding one)");
  const pickle::Dict& top = doc.dict(root);
  if (!key.empty()) {
    const pickle::Value* v = doc.find(top, key);
    EPONA_CHECK(v != nullptr, source, ": no key '", key, "' in the checkpoint; its top-level keys are ",
                list_keys(doc, top));
    EPONA_CHECK(v->kind == pickle::Kind::Dict, source, ": '", key, "' holds a ", doc.describe(*v),
                ", expected a dict of tensors");
    return *v;
  }
  if (is_dict_of_tensors(doc, root)) return root;
  for (const char* k : kStateDictKeys)
    if (const pickle::Value* v = doc.find(top, k); v && v->kind == pickle::Kind::Dict) return *v;
  fail(source,
       ": no state dict found: the top-level dict does not hold tensors only and has no dict under "
       "'model_state_dict', 'model' or 'state_dict' (pass the key explicitly); its keys are ",
       list_keys(doc, top));
}

// Row-major contiguity; extents of 0 or 1 place no constraint on their stride (as in PyTorch).
// Call with a shape whose element count does not overflow.
inline bool is_contiguous(const Shape& shape, const Shape& stride) {
  if (std::find(shape.begin(), shape.end(), 0) != shape.end()) return true;
  std::int64_t expected = 1;
  for (std::size_t d = shape.size(); d-- > 0;) {
    if (shape[d] != 1 && stride[d] != expected) return false;
    expected *= shape[d];
  }
  return true;
}

// Storage records, found once per key; the same key must always carry the same dtype.
class StorageTable {
 public:
  StorageTable(const ZipArchive& zip, std::string prefix, bool verify)
      : zip_(zip), prefix_(std::move(prefix)), verify_(verify) {}

  struct Record {
    DType dtype;
    std::span<const std::byte> bytes;
    std::string name;  // of the archive entry
  };

  const Record& get(const pickle::StorageRef& s, const std::string& tensor) {
    auto it = records_.find(s.key);
    if (it != records_.end()) {
      EPONA_CHECK(it->second.dtype == s.dtype, zip_.name(), ": storage '", s.key, "' is used as ",
                  dtype_name(it->second.dtype), " and as ", dtype_name(s.dtype), " (tensor '", printable(tensor, 200),
                  "')");
      return it->second;
    }
    const std::string record = prefix_ + "data/" + s.key;
    const ZipEntry* e = zip_.find(record);
    EPONA_CHECK(e != nullptr, zip_.name(), ": storage '", pickle::Document::printable(s.key), "' of tensor '",
                printable(tensor, 200), "' has no record '", pickle::Document::printable(record), "' in the archive");
    if (verify_) zip_.verify_crc(*e);
    return records_.emplace(s.key, Record{s.dtype, zip_.data(*e), record}).first->second;
  }

 private:
  const ZipArchive& zip_;
  std::string prefix_;
  bool verify_;
  std::map<std::string, Record> records_;
};

// The bytes of tensor `name`: contiguous, inside its storage record and its declared numel.
inline RawTensor tensor_view(const pickle::Document& doc, const pickle::TensorRef& t, const std::string& name,
                             StorageTable& storages, const std::string& source) {
  const pickle::StorageRef& s = doc.storage(t.storage);
  std::int64_t numel = 0;
  try {
    numel = shape_numel(t.shape);
  } catch (const Error& e) {
    fail(source, ": tensor '", printable(name, 200), "': ", e.what());
  }
  EPONA_CHECK(is_contiguous(t.shape, t.stride), source, ": tensor '", printable(name, 200), "' of shape ",
              shape_str(t.shape), " is not contiguous (stride ", shape_str(t.stride), "); save it with .contiguous()");
  const auto esize = static_cast<std::uint64_t>(dtype_size(s.dtype));
  const auto first = static_cast<std::uint64_t>(t.offset), count = static_cast<std::uint64_t>(numel);
  const std::uint64_t limit = ~std::uint64_t{0} / esize;
  EPONA_CHECK(count <= limit && first <= limit - count, source, ": tensor '", printable(name, 200), "' of shape ",
              shape_str(t.shape), " at storage offset ", t.offset, " overflows 64-bit byte offsets");
  const auto& record = storages.get(s, name);
  const std::uint64_t needed = (first + count) * esize;
  EPONA_CHECK(count == 0 || needed <= record.bytes.size(), source, ": tensor '", printable(name, 200), "' needs ", needed,
              " bytes (", dtype_name(s.dtype), " ", shape_str(t.shape), " at storage offset ", t.offset,
              "), storage '", s.key, "' has ", record.bytes.size());
  EPONA_CHECK(count == 0 || first + count <= static_cast<std::uint64_t>(s.numel), source, ": tensor '", printable(name, 200),
              "' needs elements up to ", first + count, ", storage '", s.key, "' declares ", s.numel);
  EPONA_CHECK(static_cast<std::uint64_t>(s.numel) <= record.bytes.size() / esize, source, ": storage '", s.key,
              "' declares ", s.numel, " elements of ", dtype_name(s.dtype), ", its record '", record.name,
              "' has only ", record.bytes.size(), " bytes");
  RawTensor r;
  r.dtype = s.dtype;
  r.shape = t.shape;
  if (count > 0)
    r.bytes =
        record.bytes.subspan(static_cast<std::size_t>(first * esize), static_cast<std::size_t>(count * esize));
  return r;
}

// torch.save records the byte order since PyTorch 2.1; older files are little-endian.
inline void check_byte_order(const ZipArchive& zip, const std::string& prefix) {
  const ZipEntry* e = zip.find(prefix + "byteorder");
  if (!e) return;
  const auto b = zip.data(*e);
  const std::string_view order(reinterpret_cast<const char*>(b.data()), b.size());
  EPONA_CHECK(order == "little", zip.name(), ": the checkpoint was written with byte order '",
              pickle::Document::printable(order), "'; only little-endian checkpoints are supported");
}

}  // namespace torch_detail

// The tensors of the chosen state dict of an opened torch.save archive.
inline TensorMap load_torch_checkpoint(const ZipArchive& zip, const TorchLoadOptions& options = {}) {
  const std::string prefix = torch_detail::archive_prefix(zip);
  torch_detail::check_byte_order(zip, prefix);
  const ZipEntry* pkl = zip.find(prefix + "data.pkl");
  EPONA_CHECK(pkl != nullptr, zip.name(), ": not a torch.save checkpoint: no '",
              pickle::Document::printable(prefix + "data.pkl"), "' in the archive");
  zip.verify_crc(*pkl);
  const pickle::Document doc = pickle::unpickle(zip.data(*pkl), zip.name() + " (" + pkl->name + ")");
  const pickle::Value state = torch_detail::select_state_dict(doc, options.key, zip.name());

  TensorMap map(zip.name());
  torch_detail::StorageTable storages(zip, prefix, options.verify_checksums);
  for (const auto& [k, v] : doc.dict(state).items) {
    EPONA_CHECK(k.kind == pickle::Kind::String, zip.name(), ": the state dict has a key that is a ",
                doc.describe(k), ", expected parameter names (str)");
    const std::string& name = doc.str(k);
    EPONA_CHECK(v.kind == pickle::Kind::Tensor, zip.name(), ": state dict entry '",
                pickle::Document::printable(name, 200), "' is a ", doc.describe(v), ", not a tensor");
    map.add(name, torch_detail::tensor_view(doc, doc.tensor(v), name, storages, zip.name()));
  }
  map.keep_alive(std::const_pointer_cast<void>(zip.owner()));
  return map;
}

inline TensorMap load_torch_checkpoint(const std::string& path, const TorchLoadOptions& options) {
  return load_torch_checkpoint(ZipArchive::open(path), options);
}
inline TensorMap load_torch_checkpoint(const std::string& path, const std::string& key = "") {
  return load_torch_checkpoint(path, TorchLoadOptions{key});
}

}  // namespace epona::io
