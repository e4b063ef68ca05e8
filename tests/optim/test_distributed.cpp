#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <random>
#include <thread>
#include <vector>

#include "flexsplat/optim/distributed.hpp"

using namespace flexsplat;

namespace {
// Ranks as threads with mailboxes: exercises the same protocol as MpiCommunicator without MPI. Messages between a
// pair of ranks arrive in the order they were sent; a broadcast is a send from the root to every other rank.
struct Mailboxes {
  std::mutex m;
  std::condition_variable cv;
  std::map<std::pair<int, int>, std::deque<std::vector<char>>> queue;  // (from, to) -> messages
  bool bad = false;  // a send to oneself or a size mismatch (Catch's assertions are not for other threads)
};

class ThreadCommunicator final : public train::Communicator {
public:
  ThreadCommunicator(Mailboxes& box, int rank, int size) : box_(box), rank_(rank), size_(size) {}
  int rank() const override { return rank_; }
  int size() const override { return size_; }
  void send_bytes(const void* d, std::size_t bytes, int to) override {
    std::lock_guard lock(box_.m);
    if (to == rank_) box_.bad = true;
    box_.queue[{rank_, to}].emplace_back(static_cast<const char*>(d), static_cast<const char*>(d) + bytes);
    box_.cv.notify_all();
  }
  void receive_bytes(void* d, std::size_t bytes, int from) override {
    std::unique_lock lock(box_.m);
    auto& q = box_.queue[{from, rank_}];
    box_.cv.wait(lock, [&] { return !q.empty(); });
    if (q.front().size() != bytes) box_.bad = true;
    std::memcpy(d, q.front().data(), std::min(bytes, q.front().size()));
    q.pop_front();
  }
  void broadcast_bytes(void* d, std::size_t bytes, int root) override {
    if (rank_ != root) return receive_bytes(d, bytes, root);
    for (int r = 0; r < size_; ++r)
      if (r != root) send_bytes(d, bytes, r);
  }

private:
  Mailboxes& box_;
  int rank_, size_;
};

std::vector<index_t> counts_of(const train::ScenePlan& p, int size) {
  std::vector<index_t> counts(static_cast<std::size_t>(size), 0);
  for (int r : p.owner) ++counts[static_cast<std::size_t>(r)];
  return counts;
}
}  // namespace

TEST_CASE("contiguous_plan splits a global batch into contiguous shares in rank order", "[train][distributed]") {
  for (int size = 1; size <= 5; ++size)
    for (index_t global = size; global <= 13; ++global) {
      const train::ScenePlan p = train::contiguous_plan(global, size);
      REQUIRE(p.global() == global);
      index_t next = 0;
      for (int r = 0; r < size; ++r) {
        const std::vector<index_t> mine = p.scenes_of(r);
        REQUIRE(!mine.empty());
        for (index_t s : mine) CHECK(s == next++);
        CHECK(static_cast<index_t>(mine.size()) == global / size + (r < global % size ? 1 : 0));
      }
      CHECK(next == global);
    }
  CHECK_THROWS_WITH(train::contiguous_plan(2, 3), Catch::Contains("global batch of 2 scenes cannot feed 3 ranks"));
  const std::vector<index_t> two{1, 2};
  CHECK_THROWS_WITH(train::balanced_plan(two, 3), Catch::Contains("global batch of 2 scenes cannot feed 3 ranks"));
}

TEST_CASE("balanced_plan keeps the contiguous counts and evens the ranks' costs", "[train][distributed]") {
  // Four scenes of 1-4 views on two ranks (the shipped recipe): every cost vector, against the best split into pairs.
  for (int code = 0; code < 256; ++code) {
    const std::vector<index_t> cost{1 + code % 4, 1 + code / 4 % 4, 1 + code / 16 % 4, 1 + code / 64};
    const train::ScenePlan p = train::balanced_plan(cost, 2);
    REQUIRE(counts_of(p, 2) == std::vector<index_t>{2, 2});
    index_t load0 = 0, total = 0;
    for (std::size_t s = 0; s < 4; ++s) total += cost[s], load0 += p.owner[s] == 0 ? cost[s] : 0;
    const index_t worst = std::max(load0, total - load0);
    index_t best = total;
    for (std::size_t partner = 1; partner < 4; ++partner) {
      const index_t pair = cost[0] + cost[partner];
      best = std::min(best, std::max(pair, total - pair));
    }
    INFO("costs " << cost[0] << " " << cost[1] << " " << cost[2] << " " << cost[3]);
    CHECK(worst == best);
  }
  // Any batch and rank count: the contiguous plan's counts per rank (as a multiset).
  std::mt19937 rng(5);
  for (int trial = 0; trial < 200; ++trial) {
    const int size = 1 + static_cast<int>(rng() % 6);
    const index_t global = size + static_cast<index_t>(rng() % 12);
    std::vector<index_t> cost(static_cast<std::size_t>(global));
    for (auto& c : cost) c = 1 + static_cast<index_t>(rng() % 8);
    const train::ScenePlan p = train::balanced_plan(cost, size);
    const std::vector<index_t> expect = counts_of(train::contiguous_plan(global, size), size);  // non-increasing
    std::vector<index_t> got = counts_of(p, size);
    std::sort(got.begin(), got.end(), std::greater<>());
    CHECK(got == expect);
  }
  // Equal costs keep the contiguous plan's counts per rank.
  const std::vector<index_t> same(5, 3);
  CHECK(counts_of(train::balanced_plan(same, 2), 2) == std::vector<index_t>{3, 2});
}

TEST_CASE("ordered_sum on any rank count and plan is bitwise the one-process sum", "[train][distributed]") {
  const index_t n = 257, global = 7;
  std::mt19937 rng(11);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  std::vector<std::vector<float>> grads(global, std::vector<float>(n));
  for (auto& g : grads)
    for (auto& v : g) v = u(rng) * std::pow(10.f, float(rng() % 7) - 3.f);  // mixed magnitudes: order matters
  auto run = [&](const train::ScenePlan& plan, int size) {
    Mailboxes box;
    std::vector<std::vector<float>> totals(size, std::vector<float>(n, -99.f));
    std::vector<double> scalars(size, -1.0);
    std::vector<std::thread> threads;
    for (int r = 0; r < size; ++r)
      threads.emplace_back([&, r] {
        ThreadCommunicator comm(box, r, size);
        std::vector<const float*> local;
        std::vector<double> values;
        for (index_t i : plan.scenes_of(r)) local.push_back(grads[i].data()), values.push_back(0.1 * double(i + 1));
        train::ordered_sum<float>(comm, totals[r].data(), n, plan, local);
        scalars[r] = train::ordered_sum<double>(comm, plan, values);
      });
    for (auto& t : threads) t.join();
    REQUIRE(!box.bad);
    for (int r = 1; r < size; ++r) {
      REQUIRE(std::memcmp(totals[r].data(), totals[0].data(), n * 4) == 0);
      REQUIRE(scalars[r] == scalars[0]);
    }
    for (const auto& q : box.queue) REQUIRE(q.second.empty());  // every message was received
    double expect = 0.1;
    for (index_t i = 1; i < global; ++i) expect += 0.1 * double(i + 1);
    CHECK(scalars[0] == expect);
    return totals[0];
  };
  const auto one = run(train::contiguous_plan(global, 1), 1);
  for (int size : {2, 3, 7}) {
    const auto many = run(train::contiguous_plan(global, size), size);
    CHECK(std::memcmp(many.data(), one.data(), n * 4) == 0);
    for (int trial = 0; trial < 5; ++trial) {  // scenes spread over the ranks in any order
      train::ScenePlan p = train::contiguous_plan(global, size);
      std::shuffle(p.owner.begin(), p.owner.end(), rng);
      const auto spread = run(p, size);
      CHECK(std::memcmp(spread.data(), one.data(), n * 4) == 0);
    }
  }
  // A plan naming a rank the communicator does not have is refused before anything is sent.
  {
    train::SoloCommunicator solo;
    train::ScenePlan bad;
    bad.owner = {0, 1};
    std::vector<const float*> local{grads[0].data()};
    std::vector<float> total(n);
    CHECK_THROWS_WITH(train::ordered_sum<float>(solo, total.data(), n, bad, local),
                      Catch::Contains("scene 1 belongs to rank 1 of 1"));
  }
  // The one-process result is the plain sequential sum.
  std::vector<float> seq(grads[0]);
  for (index_t s = 1; s < global; ++s)
    for (index_t i = 0; i < n; ++i) seq[i] += grads[s][i];
  CHECK(std::memcmp(seq.data(), one.data(), n * 4) == 0);
}
