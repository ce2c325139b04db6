// epona/io/image_folder.hpp — the frames of a folder: image files (.png/.jpg/.jpeg) in natural
// name order ("frame_2.png" before "frame_10.png"), the order every clip reader of the project
// uses (the CLI's --frames, the evaluation's clip sets).
#pragma once

#include <algorithm>
#include <cctype>
#include <filesystem>
#include <string>
#include <vector>

#include "epona/core/error.hpp"

namespace epona::io {

inline std::string lower_text(std::string s) {
  for (auto& ch : s) ch = static_cast<char>(std::tolower(static_cast<unsigned char>(ch)));
  return s;
}

inline bool is_image_file(const std::filesystem::path& p) {
  const std::string ext = lower_text(p.extension().string());
  return ext == ".png" || ext == ".jpg" || ext == ".jpeg";
}

// "frame_2.png" before "frame_10.png": digit runs compare by value, the rest byte-wise.
inline bool natural_less(const std::string& a, const std::string& b) {
  std::size_t i = 0, j = 0;
  while (i < a.size() && j < b.size()) {
    const bool da = std::isdigit(static_cast<unsigned char>(a[i])), db = std::isdigit(static_cast<unsigned char>(b[j]));
    if (da && db) {
      std::size_t ie = i, je = j;
      while (ie < a.size() && std::isdigit(static_cast<unsigned char>(a[ie]))) ++ie;
      while (je < b.size() && std::isdigit(static_cast<unsigned char>(b[je]))) ++je;
      std::string na = a.substr(i, ie - i), nb = b.substr(j, je - j);
      na.erase(0, std::min(na.find_first_not_of('0'), na.size()));
      nb.erase(0, std::min(nb.find_first_not_of('0'), nb.size()));
      if (na.size() != nb.size()) return na.size() < nb.size();
      if (na != nb) return na < nb;
      i = ie, j = je;
      continue;
    }
    if (a[i] != b[j]) return a[i] < b[j];
    ++i, ++j;
  }
  return a.size() - i < b.size() - j || (a.size() - i == b.size() - j && a < b);
}

inline void sort_natural(std::vector<std::filesystem::path>& files) {
  std::sort(files.begin(), files.end(),
            [](const auto& x, const auto& y) { return natural_less(x.filename().string(), y.filename().string()); });
}

// The image files directly in `dir`, in natural name order (possibly none). `what` names the
// folder in errors (an option, or a clip).
inline std::vector<std::filesystem::path> image_files(const std::filesystem::path& dir, const std::string& what) {
  std::error_code ec;
  EPONA_CHECK(std::filesystem::exists(dir, ec), what, " ", dir.string(), ": no such folder");
  EPONA_CHECK(std::filesystem::is_directory(dir, ec), what, " ", dir.string(), ": not a folder");
  std::vector<std::filesystem::path> files;
  for (const auto& e : std::filesystem::directory_iterator(dir, ec))
    if (e.is_regular_file() && is_image_file(e.path())) files.push_back(e.path());
  EPONA_CHECK(!ec, what, " ", dir.string(), ": cannot list the folder: ", ec.message());
  sort_natural(files);
  return files;
}

}  // namespace epona::io
