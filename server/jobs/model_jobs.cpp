#include "server/jobs/model_jobs.hpp"

#include <memory>
#include <system_error>

#include "core/common/error.hpp"
#include "core/io/grid_source.hpp"
#include "core/merge/merge.hpp"
#include "core/merge/register.hpp"
#include "core/store/live_model.hpp"

namespace vsm::server::jobs {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

json matrixJson(const core::Mat4d& m) {
  return json(m.m);
}

}  // namespace

JobStatus submitImport(JobRegistry& jobs, models::ModelRegistry& models, const std::string& id,
                       const fs::path& input, int patchSize, core::ImportOptions::Drape drape) {
  if (drape == core::ImportOptions::Drape::Image) {
    throw Error(ErrorCode::InvalidArgument, "an import job drapes no image");
  }
  models::checkModelId(id);
  if (patchSize < 3 || patchSize > 4097 || ((patchSize - 1) & (patchSize - 2)) != 0) {
    throw Error(ErrorCode::InvalidArgument,
                "patch_size must be 2^n + 1 between 3 and 4097, not " + std::to_string(patchSize));
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
  JobContext::Plan plan = {{"import", 0.95}, {"opening", 0.05}};
  return jobs.submit(
      "import", std::move(params), std::move(plan),
      [&models, reservation, id, input, outDir, patchSize, drape](JobContext& context) {
        core::ImportOptions options;
        options.patchSize = patchSize;
        options.drape = drape;
        options.progress = &context;
        options.cancel = &context.cancelToken();
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
  std::shared_ptr<core::LiveModel> targetModel = models.get(target);
  std::shared_ptr<core::LiveModel> sourceModel = models.get(source);
  if (!targetModel->writable()) {
    // A second writer over HTTP: 409 at once, naming the holder.
    throw Error(ErrorCode::Conflict, "model '" + target + "' is open for reading only: " +
                                         targetModel->readOnlyReason());
  }
  json params = {{"target", target}, {"source", source}, {"register", registerFirst}};
  JobContext::Plan plan;
  if (registerFirst) {
    plan.emplace_back("registering", 0.2);
  }
  plan.insert(plan.end(),
              {{"matching", 0.05}, {"placing", 0.55}, {"reducing", 0.15}, {"publishing", 0.05}});
  return jobs.submit(
      "merge", std::move(params), std::move(plan),
      [&models, target, targetLease, sourceLease, targetModel, sourceModel,
       registerFirst](JobContext& context) {
        json result = json::object();
        // The one edit of the target; another job editing it makes this one fail (Conflict).
        std::unique_ptr<core::ModelEdit> edit = targetModel->beginEdit();
        try {
          result["base_version"] = edit->base().version;
          core::MergeOptions options;
          options.progress = &context;
          options.cancel = &context.cancelToken();
          if (registerFirst) {
            core::RegistrationOptions registration;
            registration.progress = &context;
            registration.cancel = &context.cancelToken();
            const core::RegistrationResult registered =
                core::registerModels(*targetModel, *sourceModel, registration);
            options.transform = registered.transform;
            result["registration"] = {{"transform", matrixJson(registered.transform)},
                                      {"fitness", registered.fitness},
                                      {"converged", registered.converged},
                                      {"stages", registered.stages},
                                      {"seconds", registered.seconds}};
          }
          const core::MergeResult merged = core::mergeModels(*edit, *sourceModel, options);
          context.report("publishing", 0);
          // Cancellation is honoured up to the commit point; after it the new version is the
          // model's and the job has succeeded.
          edit->publish(&context.cancelToken(), {context.id(), models.keepRevisions()});
          result["version"] = targetModel->snapshot()->version;
          edit.reset();
          context.report("publishing", 1);
          result["matched_leaves"] = merged.matchedLeaves;
          result["detail_leaves"] = merged.detailLeaves;
          result["new_patches"] = merged.newPatches;
          result["resampled_leaves"] = merged.resampledLeaves;
          result["vertices_from_detail"] = merged.verticesFromDetail;
          result["max_levels"] = merged.maxLevels;
          result["merge_seconds"] = merged.seconds;
          return result;
        } catch (const Error& e) {
          if (e.code() == ErrorCode::Io) {
            // A failed write or sync: the drafts go, and the model is read again from disk (as
            // the old version, or the new one when only a step after the commit point failed).
            edit.reset();
            models.reopen(target);
          }
          throw;
        }
      });
}

JobStatus submitRestore(JobRegistry& jobs, models::ModelRegistry& models, const std::string& id,
                        std::uint64_t revision) {
  models::checkModelId(id);
  auto lease = std::make_shared<models::ModelRegistry::Lease>(models.lease(id));
  std::shared_ptr<core::LiveModel> model = models.get(id);
  if (!model->writable()) {
    throw Error(ErrorCode::Conflict,
                "model '" + id + "' is open for reading only: " + model->readOnlyReason());
  }
  // NotFound for a revision not kept, before a job is queued.
  std::shared_ptr<const core::ModelSnapshot> from = model->snapshotAt(revision);
  json params = {{"model", id}, {"revision", revision}};
  JobContext::Plan plan = {{"restoring", 0.8}, {"publishing", 0.2}};
  return jobs.submit(
      "restore", std::move(params), std::move(plan),
      [&models, id, lease, model, from, revision](JobContext& context) mutable {
        std::unique_ptr<core::ModelEdit> edit = model->beginEdit();
        try {
          json result = {
              {"model", id}, {"restored", revision}, {"base_version", edit->base().version}};
          context.report("restoring", 0);
          edit->restore(*from, &context.cancelToken());
          result["changed_patches"] = edit->changed().size();
          result["removed_patches"] = edit->removed().size();
          from.reset();
          context.report("publishing", 0);
          core::PublishOptions options{context.id(), models.keepRevisions(), revision};
          edit->publish(&context.cancelToken(), options);
          result["version"] = model->snapshot()->version;
          edit.reset();
          context.report("publishing", 1);
          return result;
        } catch (const Error& e) {
          if (e.code() == ErrorCode::Io) {
            edit.reset();
            models.reopen(id);
          }
          throw;
        }
      });
}

}  // namespace vsm::server::jobs
