// The narrow C interface of gdrf's bridge to libtorch's c10d (dist/mod.rs is its only
// user): a TCPStore rendezvous, a Gloo process group, where built (GDRF_NCCL) an NCCL
// group for CUDA tensors beside it, and three collectives on tch's tensors, each on the
// group of its tensor's device. Every C++ exception is caught and returned as a message:
// nothing aborts.
//
// Only exported, non-inline c10d entry points are called (constructors, collectives,
// `wait`): the gloo headers this compiles against (third_party/gloo) need not be the very
// gloo inside the wheel, and types instantiated inline here could disagree with it in layout.
#include <torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>
#include <torch/csrc/distributed/c10d/TCPStore.hpp>
#ifdef GDRF_NCCL
#include <torch/csrc/distributed/c10d/PrefixStore.hpp>
#include <torch/csrc/distributed/c10d/ProcessGroupNCCL.hpp>

#include <cstdlib>
#endif

#include <chrono>
#include <string>
#include <vector>

#include "../bridge_error.hpp"

namespace {

using gdrf::guarded;

struct Group {
  c10::intrusive_ptr<c10d::Store> store;
  c10::intrusive_ptr<c10d::ProcessGroupGloo> pg;
  int rank;
  int world;
  // CUDA tensors' group (NCCL), once gdrf_c10d_add_nccl made it.
  c10::intrusive_ptr<c10d::Backend> cuda;
};

// The group a collective on `t` runs in: NCCL for a CUDA tensor where it exists, else Gloo.
c10d::Backend& backend_for(void* group, const at::Tensor& t) {
  auto* g = static_cast<Group*>(group);
  if (t.is_cuda() && g->cuda) return *g->cuda;
  return *g->pg;
}

}  // namespace

extern "C" {

// Joins the group: rank 0 serves the store at host:port, every rank connects to it, and
// the Gloo group binds to `bind_host` (empty: the machine's own hostname, as torch's
// default). NULL on failure, with the reason in `err`.
void* gdrf_c10d_new(const char* host, int port, int rank, int world, const char* bind_host, long timeout_ms,
                    char* err, size_t err_len) {
  Group* g = nullptr;
  int failed = guarded(err, err_len, [&] {
    auto timeout = std::chrono::milliseconds(timeout_ms);
    c10d::TCPStoreOptions so;
    so.port = static_cast<std::uint16_t>(port);
    so.isServer = rank == 0;
    so.numWorkers = static_cast<std::size_t>(world);
    so.waitWorkers = true;
    so.timeout = timeout;
    auto store = c10::make_intrusive<c10d::TCPStore>(std::string(host), so);
    auto opts = c10d::ProcessGroupGloo::Options::create(timeout);
    std::string bind(bind_host);
    opts->devices.push_back(bind.empty() ? c10d::ProcessGroupGloo::createDefaultDevice()
                                         : c10d::ProcessGroupGloo::createDeviceForHostname(bind));
    auto pg = c10::make_intrusive<c10d::ProcessGroupGloo>(store, rank, world, opts);
    g = new Group{store, pg, rank, world, {}};
  });
  return failed ? nullptr : g;
}

// Sums `tensor` (an at::Tensor*, as tch holds it) over all ranks, in place.
int gdrf_c10d_allreduce_sum(void* group, void* tensor, char* err, size_t err_len) {
  return guarded(err, err_len, [&] {
    std::vector<at::Tensor> ts{*static_cast<at::Tensor*>(tensor)};
    c10d::AllreduceOptions o;
    o.reduceOp = c10d::ReduceOp::SUM;
    backend_for(group, ts[0]).allreduce(ts, o)->wait();
  });
}

// Overwrites `tensor` on every rank with rank `root`'s.
int gdrf_c10d_broadcast(void* group, void* tensor, int root, char* err, size_t err_len) {
  return guarded(err, err_len, [&] {
    std::vector<at::Tensor> ts{*static_cast<at::Tensor*>(tensor)};
    c10d::BroadcastOptions o;
    o.rootRank = root;
    backend_for(group, ts[0]).broadcast(ts, o)->wait();
  });
}

// Returns when every rank has called it (or the group's timeout has passed: an error).
int gdrf_c10d_barrier(void* group, char* err, size_t err_len) {
  return guarded(err, err_len, [&] { static_cast<Group*>(group)->pg->barrier()->wait(); });
}

// Adds the NCCL group for CUDA tensors (every rank must call it), on a prefix of the same
// store, with `wait` blocking and throwing at the timeout instead of the watchdog ending
// the process. An error in a build without NCCL.
int gdrf_c10d_add_nccl(void* group, long timeout_ms, char* err, size_t err_len) {
  return guarded(err, err_len, [&] {
#ifdef GDRF_NCCL
    auto* g = static_cast<Group*>(group);
    setenv("TORCH_NCCL_BLOCKING_WAIT", "1", 0);
    auto opts = c10d::ProcessGroupNCCL::Options::create();
    opts->timeout = std::chrono::milliseconds(timeout_ms);
    auto store = c10::make_intrusive<c10d::PrefixStore>("nccl", g->store);
    g->cuda = c10::make_intrusive<c10d::ProcessGroupNCCL>(store, g->rank, g->world, opts);
#else
    (void)group;
    (void)timeout_ms;
    throw std::runtime_error(
        "this build of gdrf has no NCCL group: it was built against a libtorch without CUDA, or without "
        "the CUDA headers scripts/setup.sh installs (nvidia-cuda-crt, nvidia-cuda-cccl)");
#endif
  });
}

void gdrf_c10d_free(void* group) {
  char ignored[1];
  guarded(ignored, sizeof ignored, [&] { delete static_cast<Group*>(group); });
}

}  // extern "C"
