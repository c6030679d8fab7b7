#include "server/jobs/model_jobs.hpp"

#include <memory>
#include <system_error>

#include "core/common/error.hpp"
#include "core/grid/texture_tile.hpp"
#include "core/io/grid_source.hpp"
#include "core/merge/merge_into.hpp"
#include "core/store/live_model.hpp"
#include "core/store/model_edit.hpp"

namespace vsm::server::jobs {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

json matrixJson(const core::Mat4d& m) {
  return json(m.m);
}

/// The lane of the jobs that write model `id`: they run one at a time, in submission order.
std::string writerLane(const std::string& id) {
  return "model:" + id;
}

/// The opening of model `id` a writing job uses, resolved when the job starts (a failed write
/// before it may have replaced the opening its submission saw). Throws core::Error(Conflict) for
/// a model this process only reads (in a cluster the writer may have moved meanwhile).
std::shared_ptr<core::LiveModel> writableModel(models::ModelRegistry& models,
                                               const std::string& id) {
  std::shared_ptr<core::LiveModel> live = models.get(id);
  if (!live->writable()) {
    // A second writer over HTTP: 409, naming the holder.
    throw Error(ErrorCode::Conflict,
                "model '" + id + "' is open for reading only: " + live->readOnlyReason());
  }
  return live;
}

/// Runs `write` (an edit of model `id` up to its publish); on an I/O error (a failed write or
/// sync) the model is read again from disk, as the old version, or the new one when only a step
/// after the commit point failed: nothing the opening holds in memory is trusted then. Rethrows.
template <typename Write>
json writingModel(models::ModelRegistry& models, const std::string& id, Write&& write) {
  try {
    return write();
  } catch (const Error& e) {
    if (e.code() == ErrorCode::Io) {
      models.reopen(id);
    }
    throw;
  }
}

}  // namespace

JobStatus submitImport(JobRegistry& jobs, models::ModelRegistry& models, const std::string& id,
                       const fs::path& input, int patchSize, core::ImportOptions::Drape drape,
                       int visibleTexelsPerQuad) {
  if (drape == core::ImportOptions::Drape::Image) {
    throw Error(ErrorCode::InvalidArgument, "an import job drapes no image");
  }
  models::checkModelId(id);
  if (patchSize < 3 || patchSize > 4097 || ((patchSize - 1) & (patchSize - 2)) != 0) {
    throw Error(ErrorCode::InvalidArgument,
                "patch_size must be 2^n + 1 between 3 and 4097, not " + std::to_string(patchSize));
  }
  if (const int k = visibleTexelsPerQuad;
      k != 0 && (drape == core::ImportOptions::Drape::None || k < 0 || (k & (k - 1)) != 0 ||
                 k > core::maxTexelsPerQuad(patchSize))) {
    throw Error(ErrorCode::InvalidArgument,
                "visible_texels_per_quad must be a power of two whose tiles ((patch_size - 1) "
                "times as many texels a side) stay within " +
                    std::to_string(core::kMaxTextureTileSize) + " texels, with a texture; not " +
                    std::to_string(k) + " at patch_size " + std::to_string(patchSize));
  }
  // Taken before anything is checked on disk, so two imports of one id cannot both pass.
  auto reservation = std::make_shared<models::ModelRegistry::Lease>(models.reserve(id));
  const fs::path outDir = models.dataRoot() / id;
  std::error_code ec;
  if (fs::exists(fs::symlink_status(outDir, ec))) {
    throw Error(ErrorCode::Conflict, "the data root has an entry '" + id +
                                         "' already (not open as a model; open it by path, or "
                                         "choose another id)");
  }
  if (!fs::is_regular_file(input, ec)) {
    throw Error(ErrorCode::NotFound, "import source is not a file");
  }
  json params = {{"id", id},
                 {"import", fs::relative(input, models.dataRoot()).generic_string()},
                 {"patch_size", patchSize},
                 {"texture", drape == core::ImportOptions::Drape::None ? "none" : "relief"}};
  if (visibleTexelsPerQuad != 0) {
    params["visible_texels_per_quad"] = visibleTexelsPerQuad;
  }
  JobContext::Plan plan = {{"import", 0.95}, {"opening", 0.05}};
  return jobs.submit("import", std::move(params), std::move(plan),
                     [&models, reservation, id, input, outDir, patchSize, drape,
                      visibleTexelsPerQuad](JobContext& context) {
                       core::ImportOptions options;
                       options.patchSize = patchSize;
                       options.drape = drape;
                       options.visibleTexelsPerQuad = visibleTexelsPerQuad;
                       options.progress = &context;
                       options.cancel = &context.cancelToken();
                       options.executor = &context.executor();
                       core::importFile(input, outDir, options);
                       context.report("opening", 0);
                       const auto live = models.openReserved(*reservation, outDir);
                       context.report("opening", 1);
                       const auto snapshot = live->snapshot();
                       return json{{"model", id},
                                   {"version", snapshot->version},
                                   {"patches", snapshot->model->patchCount()},
                                   {"depth", snapshot->model->maxDepth()},
                                   {"grid_size", snapshot->model->gridSize()}};
                     });
}

JobStatus submitMerge(JobRegistry& jobs, models::ModelRegistry& models, const std::string& target,
                      const std::string& source, bool registerFirst) {
  models::checkModelId(target, "target");
  models::checkModelId(source, "source");
  if (target == source) {
    throw Error(ErrorCode::InvalidArgument, "a model cannot be merged into itself");
  }
  auto targetLease = std::make_shared<models::ModelRegistry::Lease>(models.lease(target));
  auto sourceLease = std::make_shared<models::ModelRegistry::Lease>(models.lease(source));
  writableModel(models, target);  // 409 at once rather than a failed job
  json params = {{"target", target}, {"source", source}, {"register", registerFirst}};
  JobContext::Plan plan;
  if (registerFirst) {
    plan.emplace_back("registering", 0.2);
  }
  plan.insert(plan.end(),
              {{"matching", 0.05}, {"placing", 0.55}, {"reducing", 0.15}, {"publishing", 0.05}});
  return jobs.submit(
      "merge", std::move(params), std::move(plan),
      [&models, target, source, targetLease, sourceLease, registerFirst](JobContext& context) {
        return writingModel(models, target, [&] {
          const std::shared_ptr<core::LiveModel> targetModel = writableModel(models, target);
          const std::shared_ptr<core::LiveModel> sourceModel = models.get(source);
          core::MergeIntoOptions options;
          options.registerFirst = registerFirst;
          options.progress = &context;
          options.cancel = &context.cancelToken();
          options.merge.executor = &context.executor();
          options.publish = models.publishOptions(target, context.id());
          options.publish.executor = &context.executor();
          const core::MergeIntoResult merged = core::mergeInto(*targetModel, *sourceModel, options);
          json result = {{"base_version", merged.baseVersion}, {"version", merged.version}};
          if (const auto& registered = merged.registration) {
            result["registration"] = {{"transform", matrixJson(registered->transform)},
                                      {"fitness", registered->fitness},
                                      {"converged", registered->converged},
                                      {"stages", registered->stages},
                                      {"seconds", registered->seconds}};
          }
          result["matched_leaves"] = merged.merge.matchedLeaves;
          result["detail_leaves"] = merged.merge.detailLeaves;
          result["new_patches"] = merged.merge.newPatches;
          result["resampled_leaves"] = merged.merge.resampledLeaves;
          result["vertices_from_detail"] = merged.merge.verticesFromDetail;
          result["max_levels"] = merged.merge.maxLevels;
          result["merge_seconds"] = merged.merge.seconds;
          return result;
        });
      },
      writerLane(target));
}

JobStatus submitRestore(JobRegistry& jobs, models::ModelRegistry& models, const std::string& id,
                        std::uint64_t revision) {
  models::checkModelId(id);
  auto lease = std::make_shared<models::ModelRegistry::Lease>(models.lease(id));
  // NotFound for a revision not kept, Conflict for a model only read, before a job is queued.
  writableModel(models, id)->snapshotAt(revision);
  json params = {{"model", id}, {"revision", revision}};
  JobContext::Plan plan = {{"restoring", 0.8}, {"publishing", 0.2}};
  return jobs.submit(
      "restore", std::move(params), std::move(plan),
      [&models, id, lease, revision](JobContext& context) {
        return writingModel(models, id, [&] {
          const std::shared_ptr<core::LiveModel> model = writableModel(models, id);
          std::unique_ptr<core::ModelEdit> edit = model->beginEdit();
          // The revision as the current opening reads it (a merge queued before may have dropped
          // it meanwhile: NotFound then).
          std::shared_ptr<const core::ModelSnapshot> from = model->snapshotAt(revision);
          json result = {
              {"model", id}, {"restored", revision}, {"base_version", edit->base().version}};
          context.report("restoring", 0);
          edit->restore(*from, &context.cancelToken());
          result["changed_patches"] = edit->changed().size();
          result["removed_patches"] = edit->removed().size();
          from.reset();
          context.report("publishing", 0);
          core::PublishOptions options = models.publishOptions(id, context.id());
          options.restoredFrom = revision;
          options.executor = &context.executor();
          edit->publish(&context.cancelToken(), options);
          result["version"] = model->snapshot()->version;
          edit.reset();
          context.report("publishing", 1);
          return result;
        });
      },
      writerLane(id));
}

}  // namespace vsm::server::jobs
