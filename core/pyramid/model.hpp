#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <iterator>
#include <map>
#include <memory>
#include <string>
#include <string_view>
#include <unordered_set>
#include <utility>
#include <vector>

#include <boost/smart_ptr/intrusive_ptr.hpp>
#include <boost/smart_ptr/intrusive_ref_counter.hpp>

#include "core/grid/patch_grid.hpp"
#include "core/pyramid/patch_key.hpp"

namespace vsm::core {

struct ModelChange;
class Model;
ModelChange modelChange(const Model& before, const Model& after);

/// The names of a patch's files in its folder, as Patch.xml gives them.
struct PatchFiles {
  std::string positions = "Positions.aara";
  /// Texture coordinates (V2f per stored vertex): Patch.xml's
  /// <Coordinates><DiffuseColor1Coordinates>; empty when the patch has no texture.
  std::string coordinates;
  /// The texture tile relative to Images/ as Patch.xml names it (backslash-separated, e.g.
  /// "Diffuse\\2_0_0.tif"): the first <Textures> entry; empty when the patch has no texture.
  std::string texture;
  friend bool operator==(const PatchFiles&, const PatchFiles&) = default;
};

/// A GridRect in 8 bytes (a grid has at most 2^15 + 1 vertices a side): PatchInfo::stored.
struct PackedRect {
  std::uint16_t x0 = 0, y0 = 0, x1 = 0, y1 = 0;

  PackedRect() = default;
  /// Both throw Error(InvalidArgument) unless every coordinate fits (fits()).
  explicit PackedRect(const GridRect& rect);
  PackedRect& operator=(const GridRect& rect) { return *this = PackedRect(rect); }
  operator GridRect() const { return {x0, y0, x1, y1}; }
  static bool fits(const GridRect& rect);

  bool empty() const { return x0 >= x1 || y0 >= y1; }
  int width() const { return x1 - x0; }
  int height() const { return y1 - y0; }
  friend bool operator==(const PackedRect&, const PackedRect&) = default;
};

/// Everything known about a patch without its vertex data: always resident, so kept small (a
/// model of 10^6 patches holds 1.4 million, 168 bytes each). What vsm's own patches have in common
/// is not stored: the folder named after the key, Local2Global a translation, the untextured file
/// names; the rest (an edit's draft folder, a foreign OPC's names and matrices) is held behind one
/// pointer. Vertex data is held apart (Model::grid, the cache).
struct PatchInfo {
  PatchKey key;
  /// Bit q is set when the child in Quadrant q exists.
  std::uint8_t childMask = 0;
  /// States (thesis 3.4): changed and not yet written / an overview whose descendants changed, to
  /// be recomputed before use (and Model::grid: the vertex data is in memory).
  bool dirty = false;
  bool stale = false;
  /// A hidden level's patch (thesis 5.2, core/opc/README.md "Hidden levels"): named only in the
  /// model's second hierarchy file, which other OPC readers do not read. Its parent's item is
  /// there too; its own children are hidden as well.
  bool hidden = false;
  Box3d globalBox;
  Box3d localBox;
  /// Mean distance between defined grid neighbours, metres.
  double resolution = 0;
  /// Increases whenever the patch's data changes.
  std::uint64_t version = 1;
  /// The part of the full grid stored on disk (undefined border rows/columns are cropped).
  PackedRect stored;

  /// Directory name under Patches/: key.toString() unless set otherwise (an edit's draft folder,
  /// a foreign OPC's own names).
  std::string folder() const;
  /// The same without a copy: the stored name, or the key's written into `buffer`.
  std::string_view folder(char (&buffer)[PatchKey::kMaxText]) const;
  /// True when folder() is not key.toString().
  bool ownFolder() const { return extras_ != nullptr && !extras_->folder.empty(); }
  /// Set the key first: a name equal to key.toString() is not stored.
  void setFolder(std::string folder);

  Mat4d local2global() const {
    return extras_ && extras_->matrix ? *extras_->matrix : Mat4d::translation(translation_);
  }
  void setLocal2Global(const Mat4d& m);

  const PatchFiles& files() const {
    return extras_ && extras_->files ? *extras_->files : kUntexturedFiles;
  }
  const std::string& positionsFile() const { return files().positions; }
  const std::string& coordinatesFile() const { return files().coordinates; }
  const std::string& textureFile() const { return files().texture; }
  void setFiles(PatchFiles files);

  bool isLeaf() const { return childMask == 0; }
  bool hasChild(Quadrant q) const { return (childMask >> static_cast<int>(q)) & 1; }

  /// The heap blocks this patch holds (its folder name, matrix and file names when it has them;
  /// shared ones counted with each patch): Model::heapBytes.
  std::size_t ownHeapBytes() const;

 private:
  /// What a patch of vsm's own does not have; never changed once shared (set* replace it).
  struct Extras {
    std::string folder;                       ///< empty: key.toString()
    std::shared_ptr<const Mat4d> matrix;      ///< null: Local2Global is translation_ alone
    std::shared_ptr<const PatchFiles> files;  ///< null: kUntexturedFiles
  };
  /// Extras counted in themselves: a pointer of 8 bytes rather than a shared_ptr's 16.
  struct CountedExtras : boost::intrusive_ref_counter<CountedExtras>, Extras {
    explicit CountedExtras(Extras extras) : Extras(std::move(extras)) {}
  };
  static const PatchFiles kUntexturedFiles;
  /// extras_ replaced by a copy that `change` changed, or by null when nothing is left in it.
  template <typename Change>
  void changeExtras(Change change);

  Vec3d translation_;
  /// Null for a patch of vsm's own.
  boost::intrusive_ptr<const CountedExtras> extras_;
};

/// Per-depth summary of a model.
struct LevelSummary {
  int depth = 0;
  std::size_t patches = 0;
  std::size_t leaves = 0;
  /// Patches of a hidden level (PatchInfo::hidden); 0 in a summary read from an index.
  std::size_t hidden = 0;
  Box3d bounds;
  /// Mean of the patches' resolutions at this depth (metres), each taken in whole nanometres, so
  /// that it is exactly the same however the sum is grouped.
  double resolution = 0;
  /// The least resolution of a leaf at this depth (metres); 0 when no leaf here has one.
  double finestLeaf = 0;
};

/// The deepest level of `levels` (Model::levels) holding a patch that is not hidden: the last
/// level other OPC readers see (hidden levels lie below the visible leaves); 0 for none.
int deepestVisibleDepth(const std::vector<LevelSummary>& levels);

/// True when a level of `levels` holds a hidden patch.
bool anyHidden(const std::vector<LevelSummary>& levels);

/// The pyramid: a quadtree of patches with one root, up to four children per patch, empty patches
/// omitted, and variable depth (a leaf is the actual surface at its place, every patch above it an
/// overview). Holds metadata and states; vertex data is attached per patch when resident.
///
/// Not thread-safe; the owner serialises access (copies are independent models).
class Model {
 public:
  /// Throws Error(InvalidArgument) unless gridSize is 2^n+1 with 1 <= n <= 15.
  explicit Model(int gridSize);

  int gridSize() const { return gridSize_; }
  bool empty() const { return size_ == 0; }
  std::size_t patchCount() const { return size_; }
  /// Depth of the deepest leaf; -1 for an empty model.
  int maxDepth() const;

  const PatchInfo* find(const PatchKey& key) const;
  /// Throws Error(NotFound) for a key that is not in the model.
  const PatchInfo& at(const PatchKey& key) const;
  /// The patch to change, in a chunk of this model's own (copied when it was shared with another
  /// model). Throws as at(). Valid until the model's next insert() or eraseLeaf(), which move
  /// patches within their chunks (find(), at() and edit() move none).
  PatchInfo& edit(const PatchKey& key);
  /// The patch's metadata, unchanging while held: the pointer holds the patch's whole chunk (the
  /// model copies a chunk before it changes it while another holds it: edit()). For short holds;
  /// a copy of the PatchInfo is what to keep. Throws as at().
  std::shared_ptr<const PatchInfo> shared(const PatchKey& key) const;

  /// Adds a patch (the reference as edit()'s). Its parent must exist already (except for the
  /// root), and gets the matching child bit. Throws Error(Conflict) when the key exists,
  /// Error(InvalidArgument) when the parent is missing.
  PatchInfo& insert(PatchInfo info);
  /// Removes a leaf and clears its parent's child bit. Throws Error(NotFound) for a key not in the
  /// model, Error(InvalidArgument) for a patch with children or the root.
  void eraseLeaf(const PatchKey& key);

  std::vector<PatchKey> children(const PatchKey& key) const;
  std::vector<PatchKey> leaves() const;
  /// The leaves whose global box `meets` accepts, in key order: a descent from the root through
  /// the patches whose box it accepts. A parent's box holds its children's, so `meets` must accept
  /// a box whenever it accepts one inside it (a box or a segment meeting it, say).
  std::vector<PatchKey> leavesWhere(const std::function<bool(const Box3d&)>& meets) const;
  /// All patches as (key, info) pairs, parents before children (by depth, then row, then column);
  /// reversed(): children before parents.
  class Patches;
  Patches patches() const;

  /// The patches in runs: consecutive patches in key order that the copies of a model share until
  /// one of them changes one (its copy-on-write chunks). A run's `id` stands for its content, the
  /// same patches, for as long as it is held (nothing held elsewhere is changed in place):
  /// what memos of text derived from patches (the hierarchy's) key on.
  struct Run;
  std::vector<Run> runs() const;
  /// The id of the run holding `key`; null when the model has no such patch.
  std::shared_ptr<const void> runOf(const PatchKey& key) const;

  /// Union of the global boxes of the children of `key` (empty for a leaf).
  Box3d childrenBox(const PatchKey& key) const;

  /// Updates a patch's metadata (boxes, Local2Global, resolution, stored rectangle) from its data;
  /// changes no state. The boxes hold the grid's defined vertices and the children's boxes (OPC:
  /// a parent's box contains its children's), so describe children before their parent.
  void describe(const PatchKey& key, const PatchGrid& grid);
  /// Records new vertex data for a patch: attaches it, updates box, resolution and version, marks
  /// the patch dirty and every ancestor stale.
  void setGrid(const PatchKey& key, std::shared_ptr<const PatchGrid> grid);
  /// Attaches vertex data to a patch and changes nothing else (its own data, read from its files).
  /// Throws as at().
  void attachGrid(const PatchKey& key, std::shared_ptr<const PatchGrid> grid);
  /// The vertex data attached to `key`; null when none is (a model read from an OPC holds
  /// none: its data is in the files and the cache).
  std::shared_ptr<const PatchGrid> grid(const PatchKey& key) const;
  /// Marks `key` dirty and every ancestor stale.
  void markChanged(const PatchKey& key);

  /// Recomputes every stale overview bottom-up by reduction. `load` returns a patch's vertex data
  /// when none is attached (grid()).
  using GridLoader = std::function<std::shared_ptr<const PatchGrid>(const PatchInfo&)>;
  void refreshStale(const GridLoader& load);

  std::vector<LevelSummary> levels() const;
  /// True when some patch is a hidden level's (PatchInfo::hidden): anyHidden(levels()).
  bool hasHiddenLevels() const;
  /// True when the patch `key` has children and they are a hidden level's: its <item> belongs in
  /// the second hierarchy file (a patch's children are all hidden or all not).
  bool childrenHidden(const PatchKey& key) const;
  /// OPC's AvgGeometrySizes: mean edge length per depth, finest first, root last; maxDepth()+1
  /// entries. A depth with no measurable patch takes twice the finer depth's value.
  std::vector<double> avgGeometrySizes() const;

  /// The heap bytes of this model's metadata (its chunks with their patches, and what the patches
  /// hold on the heap; 16 bytes of allocator overhead a block), leaving out the chunks in
  /// `counted` and adding the others to it: the bytes of several models sharing chunks, each
  /// chunk once (blocks patches in different chunks share are counted with each: an upper
  /// estimate). For a model no one changes any more (a published version): each chunk keeps what
  /// it found.
  std::size_t heapBytes(std::unordered_set<const void*>& counted) const;

 private:
  friend ModelChange modelChange(const Model& before, const Model& after);

  struct ChunkSums;  // model.cpp
  /// A run of consecutive patches in key order, held by value (at most kChunkSize), and what
  /// levels() and heapBytes() summed of them: kept when a levels() found the chunk shared (so
  /// never changed in place again: writableChunk copies it) or heapBytes() was asked of a model no
  /// one changes, and dropped by writableChunk.
  struct Chunk : std::vector<PatchInfo> {
    using std::vector<PatchInfo>::vector;
    Chunk() = default;
    Chunk(const Chunk& other) : std::vector<PatchInfo>(other) {}
    Chunk& operator=(const Chunk&) = delete;
    ~Chunk();
    mutable std::atomic<const ChunkSums*> sums{nullptr};
  };
  using Chunks = std::vector<std::shared_ptr<Chunk>>;
  static constexpr std::size_t kChunkSize = 256;
  /// Where a key is or would go: chunk, index in it, and whether the entry there holds the key.
  struct Place {
    std::size_t chunk = 0;
    std::size_t index = 0;
    bool found = false;
  };
  Place locate(const PatchKey& key) const;
  static ChunkSums summarise(const Chunk& chunk);
  /// The chunk's sums: kept in it (when `keep`, or found kept), or made into `made`.
  static const ChunkSums& sumsOf(const std::shared_ptr<Chunk>& chunk, bool keep,
                                 std::unique_ptr<const ChunkSums>& made);
  /// The chunk to change: a copy of its own when another model (or a shared() pointer) holds it.
  Chunk& writableChunk(std::size_t chunk);

  int gridSize_;
  std::size_t size_ = 0;
  /// What setGrid attached, by key (empty but for models built in memory: tests, tools).
  std::map<PatchKey, std::shared_ptr<const PatchGrid>> grids_;
  /// The patches in key order, in chunks shared by the copies of a model until one of them changes
  /// a chunk (copy on write, edit()). A copy of a model of 10^6 patches copies 5,500 chunk
  /// pointers; a version a store keeps holds the chunks its change touched, and modelChange skips
  /// the chunks two versions share. Nothing shared is changed in place, so models sharing chunks
  /// may be read on other threads. By value rather than a pointer a patch: 56 bytes a patch less
  /// (the pointer, its control block, the key beside it), ~80 MB at 10^6.
  Chunks chunks_;
};

/// The patches of a Model as (key, info) pairs in key order (a view: valid while the model is
/// unchanged). Hand written rather than std::views::transform, which clang 14 (the fuzz build)
/// cannot compile with libstdc++ 12.
class Model::Patches {
 public:
  class iterator {
   public:
    using iterator_category = std::bidirectional_iterator_tag;
    using value_type = std::pair<const PatchKey&, const PatchInfo&>;
    using difference_type = std::ptrdiff_t;
    using reference = value_type;
    using pointer = void;
    iterator() = default;
    iterator(const Chunks* chunks, std::size_t chunk, std::size_t index)
        : chunks_(chunks), chunk_(chunk), index_(index) {}
    value_type operator*() const {
      const PatchInfo& info = (*(*chunks_)[chunk_])[index_];
      return {info.key, info};
    }
    iterator& operator++() {
      if (++index_ == (*chunks_)[chunk_]->size()) {
        ++chunk_;
        index_ = 0;
      }
      return *this;
    }
    iterator operator++(int) {
      iterator before = *this;
      ++*this;
      return before;
    }
    iterator& operator--() {
      if (index_ == 0) {
        index_ = (*chunks_)[--chunk_]->size();
      }
      --index_;
      return *this;
    }
    iterator operator--(int) {
      iterator before = *this;
      --*this;
      return before;
    }
    friend bool operator==(const iterator& a, const iterator& b) {
      return a.chunk_ == b.chunk_ && a.index_ == b.index_;
    }

   private:
    const Chunks* chunks_ = nullptr;
    std::size_t chunk_ = 0;
    std::size_t index_ = 0;
  };
  using reverse_iterator = std::reverse_iterator<iterator>;
  struct Reversed {
    reverse_iterator first, last;
    reverse_iterator begin() const { return first; }
    reverse_iterator end() const { return last; }
  };

  Patches(const Chunks& chunks, std::size_t size) : chunks_(&chunks), size_(size) {}
  iterator begin() const { return iterator(chunks_, 0, 0); }
  iterator end() const { return iterator(chunks_, chunks_->size(), 0); }
  std::size_t size() const { return size_; }
  bool empty() const { return size_ == 0; }
  Reversed reversed() const { return {reverse_iterator(end()), reverse_iterator(begin())}; }

 private:
  const Chunks* chunks_;
  std::size_t size_;
};

inline Model::Patches Model::patches() const {
  return Patches(chunks_, size_);
}

struct Model::Run {
  std::shared_ptr<const void> id;
  Patches::iterator begin, end;
};

/// A 64-bit digest of what a patch's entity tags name: its key, version, folder, child mask,
/// global box and Local2Global. The same in every process and build (no addresses, no seeds).
std::uint64_t patchDigest(const PatchInfo& info);
/// The digest of a model's content: its grid size mixed with the sum of its patches' digests. The
/// sum does not depend on order, so a new version's digest follows from the last one's and the
/// change (subtract the replaced and removed patches', add the changed ones'): ModelSnapshot
/// keeps it that way from publish to publish.
std::uint64_t modelDigest(const Model& model);

/// What differs between the metadata of two models, each list in key order.
struct ModelChange {
  /// Keys of `after` that `before` lacks or holds another patch at: another node not equal in any
  /// stored field (folder, child mask, boxes, Local2Global, resolution, version, stored rectangle,
  /// file names; not the states).
  std::vector<PatchKey> changed;
  /// Keys of `before` that `after` lacks.
  std::vector<PatchKey> removed;

  bool empty() const { return changed.empty() && removed.empty(); }
};
/// The change from `before` to `after`, by one walk of both in key order. Chunks the two share
/// (copy on write: a version of a LiveModel and the next) are skipped whole, so two versions of one
/// model cost about the chunks their change touched; models read apart (a replica's reopen) compare
/// field by field.
ModelChange modelChange(const Model& before, const Model& after);

}  // namespace vsm::core
