#include <catch2/catch.hpp>

#include <condition_variable>
#include <cstring>
#include <map>
#include <mutex>
#include <random>
#include <thread>
#include <vector>

#include "flexsplat/train/distributed.hpp"

using namespace flexsplat;

namespace {
// Ranks as threads with mailboxes: exercises the same protocol as MpiCommunicator without MPI.
struct Mailboxes {
  std::mutex m;
  std::condition_variable cv;
  std::map<int, std::vector<char>> to;  // destination rank -> bytes
  std::map<int, std::vector<char>> broadcast;  // root rank -> bytes (each root broadcasts once per test)
};

class ThreadCommunicator final : public train::Communicator {
public:
  ThreadCommunicator(Mailboxes& box, int rank, int size) : box_(box), rank_(rank), size_(size) {}
  int rank() const override { return rank_; }
  int size() const override { return size_; }
  void receive_partial(float* d, index_t n) override { recv(d, n * 4); }
  void receive_partial(double* d, index_t n) override { recv(d, n * 8); }
  void send_partial(const float* d, index_t n) override { send(d, n * 4); }
  void send_partial(const double* d, index_t n) override { send(d, n * 8); }
  void broadcast_from_last(float* d, index_t n) override { bcast(d, n * 4, size_ - 1); }
  void broadcast_from_last(double* d, index_t n) override { bcast(d, n * 8, size_ - 1); }
  void broadcast_from_first(float* d, index_t n) override { bcast(d, n * 4, 0); }
  void broadcast_from_first(double* d, index_t n) override { bcast(d, n * 8, 0); }

private:
  void recv(void* d, index_t bytes) {
    if (rank_ == 0) return;
    std::unique_lock lock(box_.m);
    box_.cv.wait(lock, [&] { return box_.to.count(rank_) > 0; });
    std::memcpy(d, box_.to[rank_].data(), static_cast<std::size_t>(bytes));
    box_.to.erase(rank_);
  }
  void send(const void* d, index_t bytes) {
    if (rank_ == size_ - 1) return;
    std::lock_guard lock(box_.m);
    auto& buf = box_.to[rank_ + 1];
    buf.assign(static_cast<const char*>(d), static_cast<const char*>(d) + bytes);
    box_.cv.notify_all();
  }
  void bcast(void* d, index_t bytes, int root) {
    std::unique_lock lock(box_.m);
    if (rank_ == root) {
      box_.broadcast[root].assign(static_cast<char*>(d), static_cast<char*>(d) + bytes);
      box_.cv.notify_all();
      return;
    }
    box_.cv.wait(lock, [&] { return box_.broadcast.count(root) > 0; });
    std::memcpy(d, box_.broadcast[root].data(), static_cast<std::size_t>(bytes));
  }
  Mailboxes& box_;
  int rank_, size_;
};
}  // namespace

TEST_CASE("share_of splits a global batch into contiguous shares in rank order", "[train][distributed]") {
  for (int size = 1; size <= 5; ++size)
    for (index_t global = size; global <= 13; ++global) {
      index_t next = 0;
      for (int r = 0; r < size; ++r) {
        const auto s = train::share_of(global, r, size);
        CHECK(s.first == next);
        CHECK(s.count >= 1);
        next += s.count;
      }
      CHECK(next == global);
    }
  CHECK_THROWS_WITH(train::share_of(2, 0, 3), Catch::Contains("global batch of 2 scenes cannot feed 3 ranks"));
}

TEST_CASE("ordered_sum on any rank count is bitwise the one-process sum", "[train][distributed]") {
  const index_t n = 257, global = 7;
  std::mt19937 rng(11);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  std::vector<std::vector<float>> grads(global, std::vector<float>(n));
  for (auto& g : grads)
    for (auto& v : g) v = u(rng) * std::pow(10.f, float(rng() % 7) - 3.f);  // mixed magnitudes: order matters
  auto run = [&](int size) {
    Mailboxes box;
    std::vector<std::vector<float>> totals(size, std::vector<float>(n, -99.f));
    std::vector<std::thread> threads;
    for (int r = 0; r < size; ++r)
      threads.emplace_back([&, r] {
        ThreadCommunicator comm(box, r, size);
        const auto s = train::share_of(global, r, size);
        std::vector<const float*> local;
        for (index_t i = s.first; i < s.first + s.count; ++i) local.push_back(grads[i].data());
        train::ordered_sum<float>(comm, totals[r].data(), n, local);
      });
    for (auto& t : threads) t.join();
    for (int r = 1; r < size; ++r) REQUIRE(std::memcmp(totals[r].data(), totals[0].data(), n * 4) == 0);
    return totals[0];
  };
  const auto one = run(1);
  for (int size : {2, 3, 7}) {
    const auto many = run(size);
    CHECK(std::memcmp(many.data(), one.data(), n * 4) == 0);
  }
  // The one-process result is the plain sequential sum.
  std::vector<float> seq(grads[0]);
  for (index_t s = 1; s < global; ++s)
    for (index_t i = 0; i < n; ++i) seq[i] += grads[s][i];
  CHECK(std::memcmp(seq.data(), one.data(), n * 4) == 0);
}
